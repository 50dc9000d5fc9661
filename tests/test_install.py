"""The package installs (`pip install -e .`) and its console scripts run from any folder."""

import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

import train_fixtures as tf
from train_fixtures import cache_dir, demo_root  # noqa: F401  (pytest fixtures)

pytestmark = pytest.mark.slow  # the slow lane: builds and installs the package


def _source_copy(tmp_path: Path) -> Path:
    """The repository's sources copied, so that building writes nothing into the checkout."""
    source = tmp_path / "source"
    shutil.copytree(tf.REPO_ROOT, source, symlinks=True, ignore=shutil.ignore_patterns(
        ".git", "runs", "build", "*.egg-info", "__pycache__", ".*cache*", ".hypothesis",
        "results"))
    return source


def test_an_editable_install_runs_the_demo_training_from_another_folder(tmp_path, cache_dir,
                                                                        demo_root):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    # The new environment sees the suite's installed requirements (installing them again would
    # download gigabytes); the package itself comes only from the editable install.
    site = Path(subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_paths()"
                                "['purelib'])"], capture_output=True, text=True,
                               check=True).stdout.strip())
    (site / "requirements.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    install = subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet", "--no-deps",
         "--no-build-isolation", "-e", str(_source_copy(tmp_path))],
        capture_output=True, text=True, timeout=600)
    assert install.returncode == 0, install.stderr[-3000:]

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in tf.env(cache_dir).items() if k != "PYTHONPATH"}
    result = subprocess.run(
        [venv / "bin" / "pi0-armfix-train", "--config=configs/uniform.py", "--workdir=run",
         *tf.flags(tf.tiny_overrides(demo_root))],
        cwd=elsewhere, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert (elsewhere / "run" / "checkpoints" / "2").is_dir()
    assert not os.path.exists(elsewhere / "configs")  # the installed config was found


def test_a_built_wheel_ships_the_configs_and_data_inside_the_package_and_no_top_level_configs(tmp_path):
    built = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation",
         "--wheel-dir", str(tmp_path), str(_source_copy(tmp_path))],
        capture_output=True, text=True, timeout=600)
    assert built.returncode == 0, built.stderr[-3000:]
    (wheel,) = tmp_path.glob("*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    shipped = {Path(n).stem for n in names if n.startswith("pi0_armfix/configs/")}
    assert shipped == {p.stem for p in (tf.REPO_ROOT / "pi0_armfix" / "configs").glob("*.py")}
    assert not [n for n in names if n.split("/")[0] == "configs"]
    assert "pi0_armfix/reference/b1k_2025_norm_stats.json" in names  # the demo world poses from it
