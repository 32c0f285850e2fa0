"""The committed generated protobuf modules must match what protoc generates from proto/ now."""

from pathlib import Path

from haa.pb import generate

ROOT = Path(__file__).resolve().parents[1]


def test_generated_modules_are_fresh(tmp_path):
    written = generate.generate(tmp_path)
    assert written, "protoc wrote nothing"
    for new in written:
        rel = new.relative_to(tmp_path)
        committed = ROOT / rel
        assert committed.exists(), f"{rel} is not committed: run `make proto`"
        assert committed.read_text() == new.read_text(), f"{rel} is stale: run `make proto`"


def test_generated_modules_import():
    from haa.pb import control_pb2, control_pb2_grpc, hostlink_pb2, hostlink_pb2_grpc

    env = hostlink_pb2.Envelope(sender="h1", sender_incarnation=3)
    env.heartbeat.seq = 7
    again = hostlink_pb2.Envelope.FromString(env.SerializeToString())
    assert again.WhichOneof("payload") == "heartbeat" and again.heartbeat.seq == 7
    assert hasattr(hostlink_pb2_grpc, "HostLinkStub") and hasattr(control_pb2_grpc, "HostControlStub")
    assert control_pb2.StatusReply(name="x").name == "x"
