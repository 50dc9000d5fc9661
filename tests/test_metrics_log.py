"""metrics.jsonl survives a kill mid-write: a torn last line never blocks a resume; the
TensorBoard mirror is TensorBoard's own format."""

import json
import os
import subprocess
import sys

import pytest
from train_fixtures import REPO_ROOT

from pi0_armfix.training import tensorboard_events
from pi0_armfix.training.metrics_log import METRICS_FILE, MetricsWriter, read_metrics


def _write(path, text):
    path.write_text(text)
    return path


def test_a_torn_last_line_is_dropped(tmp_path):
    path = _write(tmp_path / METRICS_FILE, '{"step": 5, "loss": 1.0}\n{"step": 10, "lo')
    assert read_metrics(path) == [{"step": 5, "loss": 1.0}]


def test_a_resume_after_a_torn_line_rewrites_a_clean_file(tmp_path):
    _write(tmp_path / METRICS_FILE, '{"step": 5, "loss": 1.0}\n{"step": 10, "loss": 0.5}\n'
                                    '{"step": 15, "lo')
    writer = MetricsWriter(tmp_path, resume_step=10)
    writer.write(15, {"loss": 0.25})
    writer.close()
    lines = (tmp_path / METRICS_FILE).read_text().splitlines()
    assert [json.loads(line)["step"] for line in lines] == [5, 10, 15]


def test_a_damaged_line_before_the_last_is_named(tmp_path):
    path = _write(tmp_path / METRICS_FILE, '{"step": 5}\nnot json\n{"step": 15}\n')
    with pytest.raises(ValueError, match=rf"{METRICS_FILE} line 2 is not a JSON record"):
        read_metrics(path)


def _events(tmp_path):
    """The run's events, read with tensorboardX's own protocol buffers and CRC-32C."""
    from tensorboardX.record_writer import masked_crc32c
    from tensorboardX.proto import event_pb2

    path, = (tmp_path / "tensorboard").glob("events.out.tfevents.*")
    data, events = path.read_bytes(), []
    while data:  # TFRecord: length (8), its crc (4), the event, its crc (4)
        length = int.from_bytes(data[:8], "little")
        assert int.from_bytes(data[8:12], "little") == masked_crc32c(data[:8])
        body = data[12:12 + length]
        assert int.from_bytes(data[12 + length:16 + length], "little") == masked_crc32c(body)
        events.append(event_pb2.Event.FromString(body))
        data = data[16 + length:]
    return events


def test_every_record_is_mirrored_to_tensorboard_with_its_step(tmp_path):
    writer = MetricsWriter(tmp_path)
    writer.write(5, {"loss": 0.5, "note": "text"})
    writer.write(10, {"loss": 0.25, "skill/arm": float("nan")})
    writer.close()
    events = _events(tmp_path)
    assert events[0].file_version == tensorboard_events.FILE_VERSION
    scalars = [(e.step, v.tag, v.simple_value) for e in events for v in e.summary.value]
    assert scalars == [(5, "loss", 0.5), (10, "loss", 0.25)]


def test_the_crc_is_castagnolis():
    assert tensorboard_events.crc32c(b"123456789") == 0xE3069283  # RFC 3720's check value


def test_an_event_encodes_as_tensorboards_protocol_buffer():
    from tensorboardX.proto import event_pb2, summary_pb2

    scalars = {"loss": 0.125, "skill/left_arm": -3.5, "été": 1e30}
    for step in (1, 300, 2**40, -7):
        expected = event_pb2.Event(wall_time=1.5e9, step=step, summary=summary_pb2.Summary(
            value=[summary_pb2.Summary.Value(tag=t, simple_value=v) for t, v in scalars.items()]))
        got = tensorboard_events.encode_event(1.5e9, step, scalars=scalars)
        assert event_pb2.Event.FromString(got) == expected
        assert got == expected.SerializeToString()


def test_a_full_disk_stops_the_tensorboard_mirror_in_one_line_and_the_records_go_on(
        tmp_path, monkeypatch, caplog):
    writer = MetricsWriter(tmp_path)

    def full(*_):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(tensorboard_events.EventFile, "_write", full)
    writer.write(1, {"loss": 1.0})
    writer.write(2, {"loss": 0.5})
    writer.close()  # nothing left to flush into the same error, at close or at exit
    assert [r["step"] for r in read_metrics(tmp_path / METRICS_FILE)] == [1, 2]
    stopped = [r for r in caplog.records if "TensorBoard mirror stopped" in r.getMessage()]
    assert len(stopped) == 1 and "No space left on device" in stopped[0].getMessage()


def test_the_training_command_starts_without_torch():
    # torch (through tensorboardX) was a third of the command's start; only the mirror needs it
    code = "import sys, pi0_armfix.train; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env=dict(os.environ, PYTHONPATH=str(REPO_ROOT)))
    assert out.stdout.strip() == "False"
