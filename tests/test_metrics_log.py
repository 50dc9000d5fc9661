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
