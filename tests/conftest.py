"""Shared pytest setup: the repository on sys.path, deterministic CPU-only JAX at full precision."""

import os
import sys
import tempfile
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
# A persistent compilation cache per test process: the tiny programs that many tests compile alike
# (the tiny model's init, sampler and train steps) compile once. Subprocesses get their own
# (`train_fixtures.env`).
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR",
                      tempfile.mkdtemp(prefix="pi0_armfix_test_jax_cache_"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
