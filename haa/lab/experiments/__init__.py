"""The thesis' experiments and HAA's own benchmarks, as a library: each module runs one measurement and returns
its figures as plain data (lists of row dicts, dicts) — the same dicts `haactl bench X` writes to
`bench-results/<X>.json`, so their keys are a public interface. Nothing here prints a table: `haactl bench`
(haactl/bench.py) lays the results out with its one table helper (haactl/tables.py) and writes the JSON
(haa.lab.benchresults.write_json, with the machine description of haa.lab.benchresults.machine).

One module per experiment, named after it:

| module | `haactl bench` | what | thesis |
|---|---|---|---|
| `ufd` | `ufd` | failure detector: heartbeat rate per QoS, measured QoS in simulation | Alg. 1, §4.4 |
| `ap1` | `ap1` | OAC latency and messages vs. participants, real haa-hostd processes | §7.2.1 |
| `ap2` | `ap2` | join, leave and removal delays of the host group | §7.2.2 |
| `ap3` | `ap3`, `alloc-quality` | allocation time and messages (simulated), allocation quality | §7.2.3 |
| `ap3real` | `ap3 --real` | AP-3 on real hosts and agent processes | §7.2.3 |
| `ap4` | `ap4` | spawn, freeze, transfer and recovery delays vs. hosts | §7.2.4 |
| `agents` | `agents` | the agent runtime alone: spawn, freeze/thaw, kill -9, memory, throughput (`localhosts`) | |
| `slam` | `slam`, `ap5.1`, `ap5.2` | JC-SLAM speed; strategies at constrained capacity; delayed updates | §7.2.5 |
| `replica` | `replica` | the SLAM state in the DDB: apply cost, checkpoints, published map | §5.2.3, §6.2 |
| `ddb` | `ddb` | DDB writes through OAC: client loads, all hosts writing, the sequencer | §4.7 |
| `memory` | `memory` | RSS and event-loop stalls under maximum-size requests | |
| `idle` | `idle` | CPU and memory of an idle membership-mode cluster | |
| `sim` | `sim` | the robot simulator's stepping, camera and sonar speed | |
| `demo` | (`haactl demo`) | agents while hosts join, retire, crash: nothing lost, reordered, run twice | §7.1 |

Experiments that start hosts use haa.cluster.hostprocs (real haa-hostd processes on loopback); the agent
runtime's benchmark drives AgentSupervisor directly (`agents`, with `localhosts.LocalHosts`). The package sits
above haa.cluster, haa.lab.dsim, haa.hostd, haa.agents and haa.slam in the import layers (.importlinter) and is
imported by haactl (and the tests) only.
"""
