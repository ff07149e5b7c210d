#!/usr/bin/env bash
# Where rpo_jax's update loses to the PureJaxRL-style loop on a GPU (issue 32), in one prepared run
# of about 8 minutes on one GPU:
#
#   benchmarks/device_gap.sh [--cpu-smoke] [OUTDIR]     # OUTDIR: default $OUT if set, else ./device-gap
#
# compare.py's work at 4096 environments: phases.py (each phase of both trainers timed, the epochs'
# arithmetic rate, kernels per gradient step), ablate.py (rpo_jax's update with one change at a
# time, the changes that may weigh on a GPU), chunk_timing.py (the command line's chunks, each
# waited for, against the host's work between them), and compare.py's training steps/s of the
# command line, the library and the loop, each a fresh process. (kernel_profile.py's GPU trace
# took over 70 s to write: run it apart.)
# Each step has its own time limit; a failed or timed-out step is recorded and the others go on.
# Writes OUTDIR/<step>.log and .status.json and OUTDIR/status.txt. --cpu-smoke: the same steps at
# 64 environments, one round, to check on a CPU that the script works before GPU time is spent on it.
# PYTHON and the wheels as for device_check.sh.
set -uo pipefail
cd "$(dirname "$0")"
smoke=0
if [ "${1:-}" = "--cpu-smoke" ]; then smoke=1; shift; fi
out_dir=$(mkdir -p "${1:-${OUT:-./device-gap}}" && cd "${1:-${OUT:-./device-gap}}" && pwd)
source run_step.sh
python=$(benchmark_python "$PWD/..") || exit 2
export PYTHONPATH="$PWD/..:$PWD${PYTHONPATH:+:$PYTHONPATH}"
if [ "$smoke" = 1 ]; then
    envs=64; rounds=1; limits=(300 600 300 300); timesteps=$((64 * 32 * 4))
else
    # Seconds per step, 490 in all on an H200: phases took 72 s there, a variant of ablate's
    # compiles in about 15 s.
    envs=4096; rounds=7; limits=(110 200 45 45); timesteps=4194304
fi
variants=("no loss metrics" "no approx_kl, no clip fraction" "actor and critic fused" "all minibatches unrolled"
    "shuffled by jax.random.permutation" "GAE unrolled by 32" "every final observation valued")

run_step phases "${limits[0]}" "$python" phases.py --num-envs "$envs" --rounds "$rounds" --json "$out_dir/phases.json"
run_step ablate "${limits[1]}" "$python" ablate.py --num-envs "$envs" --rounds "$rounds" --variants "${variants[@]}"
rm -rf "$out_dir/cli"
run_step chunks "${limits[2]}" "$python" chunk_timing.py "$envs" "$out_dir/cli" "$timesteps"
rm -rf "$out_dir/cli"
for trainer in rpo_jax-cli rpo_jax purejaxrl; do
    run_step "compare-$trainer" "${limits[3]}" "$python" compare.py --measure "$trainer" --num-envs "$envs" --timesteps "$timesteps"
done
"$python" -c "import jax; print(jax.__version__, jax.devices())" >>"$out_dir/status.txt" 2>&1
