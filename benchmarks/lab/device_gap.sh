#!/usr/bin/env bash
# Where rpo_jax's update loses to the PureJaxRL-style loop on a GPU, in one prepared run of a few
# minutes on one GPU:
#
#   benchmarks/lab/device_gap.sh [--cpu-smoke] [OUTDIR]     # OUTDIR: default $OUT if set, else ./device-gap
#
# compare.py's work at 4096 environments: phases.py (each phase of both trainers timed, the epochs'
# arithmetic rate, kernels per gradient step), then compare.py's training steps/s of the command
# line, the library and the loop, each a fresh process (the command line queues its next chunk
# before the host reads the last one's outputs; on the GPU that is still to be measured).
# Each step has its own time limit; a failed or timed-out step is recorded and the others go on.
# Writes OUTDIR/<step>.log and .status.json and OUTDIR/status.txt. --cpu-smoke: the same steps at
# 64 environments, one round, to check on a CPU that the script works before GPU time is spent on it.
# PYTHON and the wheels as for benchmarks/device_check.sh.
set -uo pipefail
cd "$(dirname "$0")/.."
smoke=0
if [ "${1:-}" = "--cpu-smoke" ]; then smoke=1; shift; fi
out_dir=$(mkdir -p "${1:-${OUT:-./device-gap}}" && cd "${1:-${OUT:-./device-gap}}" && pwd)
source run_step.sh
python=$(benchmark_python "$PWD/..") || exit 2
export PYTHONPATH="$PWD/..:$PWD${PYTHONPATH:+:$PYTHONPATH}"
if [ "$smoke" = 1 ]; then
    envs=64; rounds=1; limits=(300 300); timesteps=$((64 * 32 * 4))
else
    # Seconds per step: phases took 72 s on an H200.
    envs=4096; rounds=7; limits=(110 45); timesteps=4194304
fi

run_step phases "${limits[0]}" "$python" lab/phases.py --num-envs "$envs" --rounds "$rounds" --json "$out_dir/phases.json"
for trainer in rpo_jax-cli rpo_jax purejaxrl; do
    run_step "compare-$trainer" "${limits[1]}" "$python" compare.py --measure "$trainer" --num-envs "$envs" --timesteps "$timesteps"
done
"$python" -c "import jax; print(jax.__version__, jax.devices())" >>"$out_dir/status.txt" 2>&1
