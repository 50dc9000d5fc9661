"""Shared pytest setup: the repository on sys.path, deterministic CPU-only JAX at full precision."""

import os
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))
os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("JAX_DEFAULT_MATMUL_PRECISION", "highest")
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
# XLA's cheapest CPU code generation: the suite's programs are tiny and compile about twice as
# fast; every comparison in a test is made under the same flags (subprocesses get them too,
# `train_fixtures.env`).
os.environ.setdefault("XLA_FLAGS", "--xla_backend_optimization_level=0")
