"""metrics.jsonl survives a kill mid-write: a torn last line never blocks a resume."""

import json

import pytest

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
    from tensorboardX.proto import event_pb2

    path, = (tmp_path / "tensorboard").glob("events.out.tfevents.*")
    data, events = path.read_bytes(), []
    while data:  # TFRecord: length (8), its crc (4), the event, its crc (4)
        length = int.from_bytes(data[:8], "little")
        events.append(event_pb2.Event.FromString(data[12:12 + length]))
        data = data[16 + length:]
    return events


def test_every_record_is_mirrored_to_tensorboard_with_its_step(tmp_path):
    writer = MetricsWriter(tmp_path)
    writer.write(5, {"loss": 0.5, "note": "text"})
    writer.write(10, {"loss": 0.25, "skill/arm": float("nan")})
    writer.close()
    scalars = [(e.step, v.tag, v.simple_value) for e in _events(tmp_path) for v in e.summary.value]
    assert scalars == [(5, "loss", 0.5), (10, "loss", 0.25)]


def test_a_full_disk_stops_the_tensorboard_mirror_in_one_line_and_the_records_go_on(
        tmp_path, monkeypatch, caplog):
    from tensorboardX import record_writer

    writer = MetricsWriter(tmp_path)

    def full(*_):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(record_writer.RecordWriter, "flush", full)
    writer.write(1, {"loss": 1.0})
    writer.write(2, {"loss": 0.5})
    writer.close()  # nothing left to flush into the same error, at close or at exit
    assert [r["step"] for r in read_metrics(tmp_path / METRICS_FILE)] == [1, 2]
    stopped = [r for r in caplog.records if "TensorBoard mirror stopped" in r.getMessage()]
    assert len(stopped) == 1 and "No space left on device" in stopped[0].getMessage()
