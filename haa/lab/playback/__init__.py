"""AgentPlayback (thesis §6.1.4, Table 6.1-1; docs/playback.md): recording every external input of every agent
and re-running one agent offline from its recording.

* `haa.sdk.recorder` — `Recorder`, the tap an agent process installs on its `AgentContext` when
  `HAA_RECORD_DIR` is set (haa-hostd `--record DIR`, `haactl mission run --record DIR`; the host names
  `recorder.from_env` in HAA_AGENT_TAP, haa.sdk.tap, so the agents never import this package): MCAP segments of
  protobuf messages (proto/haa/pb/playback.proto), one folder per agent, rotated by size, flushed every second.
* `haa.sdk.external` — inputs that bypass the host (haa-sim's replies to an avatar agent): a recording
  proxy of a gRPC stub and its offline stand-in.
* `haa.lab.playback.reader` — reads a recording folder or file (a crashed writer's truncated file too).
* `haa.lab.playback.replay` — re-runs one agent instance from its recorded inputs and compares every output.
"""
