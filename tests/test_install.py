"""The package installs (`pip install -e .`) and its console scripts run from any folder."""

import os
import subprocess
import sys
import sysconfig
from pathlib import Path

import train_fixtures as tf
from train_fixtures import cache_dir, demo_root  # noqa: F401  (pytest fixtures)


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
         "--no-build-isolation", "-e", str(tf.REPO_ROOT)],
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
