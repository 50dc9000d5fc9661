#!/usr/bin/env bash
# N training processes on this host, connected through jax.distributed, each with its own CPU
# devices: the multi-process code path (per-process data shards, cross-process collectives,
# multi-process checkpoints) on one machine.
#
#   launch/local.sh N --config=configs/arm_focused.py [--workdir=DIR] [--config.a.b=v ...]
#
# Environment: DEVICES_PER_PROCESS (CPU devices per process, default 1), PORT (coordinator port,
# default: a free one), PYTHON (default: python). All processes share the run folder.
set -euo pipefail

if [[ $# -lt 1 || ! "$1" =~ ^[1-9][0-9]*$ ]]; then
  echo "usage: launch/local.sh N --config=configs/<name>.py [train flags...]" >&2
  exit 2
fi
num_processes=$1
shift
python=${PYTHON:-python}
port=${PORT:-$("$python" -c 'import socket; s = socket.socket(); s.bind(("", 0)); print(s.getsockname()[1])')}
devices=${DEVICES_PER_PROCESS:-1}

pids=()
trap 'kill "${pids[@]}" 2>/dev/null || true' INT TERM EXIT
for ((i = 0; i < num_processes; i++)); do
  JAX_PLATFORMS=cpu XLA_FLAGS="--xla_force_host_platform_device_count=$devices ${XLA_FLAGS:-}" \
    "$python" -m pi0_armfix.train "$@" --num_processes="$num_processes" \
    --coordinator_address="localhost:$port" --process_id="$i" &
  pids+=($!)
done
status=0
for pid in "${pids[@]}"; do
  wait "$pid" || status=$?
done
trap - EXIT
exit "$status"
