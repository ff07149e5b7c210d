#!/usr/bin/env bash
# Every GPU figure the project claims or aims for, in one prepared run (under 10 minutes on one GPU).
#
#   benchmarks/device_check.sh [--cpu-smoke | --robots] [OUTDIR]
#
#   --cpu-smoke  the same steps at tiny sizes, side by side on the CPU's cores; its figures mean nothing
#   --robots     instead, the Go1 joystick on MJX at MuJoCo Playground's config (go1-joystick preset,
#                8192 envs, 20M steps), timed to its return (a second command: its compile alone is minutes)
#   OUTDIR       where the logs and results go (default: $OUT if set, else ./device-check)
#   -h, --help   print this text
#   PYTHON=...   (environment) the interpreter to run (default: .venv's, else python3 on the PATH)
#
# | figure | aim | measured by |
# |---|---|---|
# | raw cartpole steps/s, 4096 envs | >= 5M | benchmarks/throughput.py (env_sps) |
# | 100M-step RPO cartpole run (isaacgym preset, 4096 envs): wall and compile s | wall < 60 s | python -m rpo_jax.train |
# | 10 vmapped seeds against one | < 3x | benchmarks/seeds.py |
# | ballbalance, mjx-dmc/walker-walk training steps/s, 4096 envs | - | benchmarks/throughput.py (train_sps) |
# | one update of host-side dmc/walker-walk, the GPU's callback path (without envpool: gymnasium/Pendulum-v1) | runs | python -m rpo_jax.train |
# | training steps/s against devices, both placements (more than one device only) | - | benchmarks/scaling.py |
# | --robots: mjx-robot/Go1JoystickFlatTerrain, 20M steps: wall, compile, steps/s, return | Playground: 200M in ~7 min (RTX 4090) | python -m rpo_jax.train |
#
# Each step has its own time limit; a failed or timed-out step is recorded and the others go on.
# Writes OUTDIR/<step>.log, .status.json and the step's own .json, OUTDIR/status.txt, OUTDIR/results.json
# and OUTDIR/results.md (a Markdown table).
# --cpu-smoke checks on a CPU that the script works before GPU time is spent on it (scaling over
# the CPU made 2 devices). Its steps run side by side, as many at a time as there are cores: their
# time is XLA compiling, on one core each.
# On a machine whose Python already holds JAX and which cannot download, install the wheels of
# benchmarks/requirements-beside-jax.txt first (its header says how).
set -uo pipefail
case "${1:-}" in
    -h | --help)
        # The comment block above, without its marks.
        awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' "$0"
        exit 0
        ;;
esac
cd "$(dirname "$0")/.."
smoke=0 robots=0
if [ "${1:-}" = "--cpu-smoke" ]; then smoke=1; shift; elif [ "${1:-}" = "--robots" ]; then robots=1; shift; fi
if [ "${1:-}" != "${1#-}" ] || [ $# -gt 1 ]; then
    echo "usage: benchmarks/device_check.sh [--cpu-smoke | --robots] [OUTDIR]   (--help says more)" >&2
    exit 2
fi
out_dir=${1:-${OUT:-./device-check}}
mkdir -p "$out_dir"
source benchmarks/run_step.sh
python=$(benchmark_python "$PWD") || exit 2
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"

if [ "$smoke" = 1 ]; then
    envs=64; env_steps=20; updates=2; long_steps=$((64 * 16 * 4)); seeds_steps=$((64 * 16 * 2))
    limits=(120 120 120 120 120 120 120)
    lanes=$(nproc)
    scaling=(--cpu-devices 2 --devices 2 --num-envs 64 --runs 2 --updates 2 --repeats 1)
    # The smoke's time is XLA's CPU compiler's: without its optimisation passes the same programs
    # compile faster (mjx-dmc/walker-walk's training program: 13 s, not 19, on 2 cores) and run
    # slower, which at these sizes costs nothing.
    export XLA_FLAGS="${XLA_FLAGS:+$XLA_FLAGS }--xla_backend_optimization_level=0"
else
    envs=4096; env_steps=500; updates=10; long_steps=100000000; seeds_steps=$((4096 * 16 * 50))
    # Seconds per step, 570 in all on one GPU (630 with scaling): cartpole, cartpole-long, seeds, ballbalance,
    # mjx-walker, host-walker, scaling. MuJoCo's programs took over 60 and 80 s to compile and run on an H200.
    limits=(70 110 80 120 150 40 60)
    lanes=1  # one step at a time: each has the GPU to itself
    scaling=(--num-envs 4096 --runs 8 --updates 10 --repeats 2)
fi

# step NAME SECONDS COMMAND...: run_step, in the background while fewer than $lanes steps run.
step() {
    if [ "$lanes" -eq 1 ]; then
        run_step "$@"
        return
    fi
    while [ "$(jobs -rp | wc -l)" -ge "$lanes" ]; do wait -n; done
    run_step "$@" &
}

if [ "$robots" = 1 ]; then
    rm -rf "$out_dir/go1"
    run_step go1 540 "$python" -m rpo_jax.train --env mjx-robot/Go1JoystickFlatTerrain --preset go1-joystick --algo ppo \
        --total-timesteps 20000000 --checkpoint-every 0 --eval-every 0 --quiet --out "$out_dir/go1"
    "$python" - "$out_dir" <<'EOF'
import json, sys
from pathlib import Path

out = Path(sys.argv[1])
status = json.loads((out / "go1.status.json").read_text())
summary = json.loads((out / "go1" / "summary.json").read_text()) if (out / "go1" / "summary.json").is_file() else {}
keys = ("device", "total_timesteps", "compile_seconds", "train_seconds", "sps", "final_return_mean")
result = {"exit_code": status["exit_code"], "wall_seconds": status["wall_seconds"], **{key: summary.get(key) for key in keys}}
(out / "robots.json").write_text(json.dumps(result, indent=2))
print(json.dumps(result, indent=2))
EOF
    exit 0
fi
step cartpole "${limits[0]}" "$python" benchmarks/throughput.py --env cartpole --num-envs "$envs" --env-steps "$env_steps" \
    --train-updates "$updates" --repeats 2 --json "$out_dir/cartpole.json"
rm -rf "$out_dir/cartpole-long"
step cartpole-long "${limits[1]}" "$python" -m rpo_jax.train --env cartpole --preset isaacgym --algo rpo --num-envs "$envs" \
    --total-timesteps "$long_steps" --checkpoint-every 0 --quiet --out "$out_dir/cartpole-long"
step seeds "${limits[2]}" "$python" benchmarks/seeds.py --env cartpole --preset isaacgym --num-envs "$envs" --seeds 10 \
    --total-timesteps "$seeds_steps" --repeats 1 --json "$out_dir/seeds.json"
step ballbalance "${limits[3]}" "$python" benchmarks/throughput.py --env ballbalance --preset isaacgym-ballbalance \
    --num-envs "$envs" --env-steps "$env_steps" --train-updates "$updates" --repeats 1 --json "$out_dir/ballbalance.json"
step mjx-walker "${limits[4]}" "$python" benchmarks/throughput.py --env mjx-dmc/walker-walk --num-envs "$envs" \
    --env-steps "$env_steps" --train-updates "$updates" --repeats 1 --json "$out_dir/mjx-walker.json"
rm -rf "$out_dir/host-walker"
host_env=dmc/walker-walk
# envpool's wheels with their assets are over 100 MB: a Gymnasium simulator takes the same callbacks.
"$python" -c "import envpool" 2>/dev/null || host_env=gymnasium/Pendulum-v1
echo "$host_env" >"$out_dir/host-walker.env"
step host-walker "${limits[5]}" "$python" -m rpo_jax.train --env "$host_env" --num-envs 64 --num-steps 32 \
    --total-timesteps 2048 --checkpoint-every 0 --quiet --out "$out_dir/host-walker"
device_count=$("$python" -c "import jax; print(len(jax.local_devices()))" 2>/dev/null || echo 1)
if [ "$smoke" = 1 ] || [ "$device_count" -gt 1 ]; then
    step scaling "${limits[6]}" "$python" benchmarks/scaling.py --env cartpole "${scaling[@]}" --json "$out_dir/scaling.json"
fi
wait

"$python" - "$out_dir" "$smoke" <<'EOF'
import importlib.metadata
import json
import platform
import sys
from pathlib import Path

out, smoke = Path(sys.argv[1]), sys.argv[2] == "1"
read = lambda name: json.loads((out / name).read_text()) if (out / name).is_file() else None
status = {path.name.removesuffix(".status.json"): json.loads(path.read_text()) for path in sorted(out.glob("*.status.json"))}
rows = []  # (figure, value, aim, step)
if cartpole := read("cartpole.json"):
    rows += [("raw cartpole env steps/s", f"{cartpole['env_sps']:,.0f}", ">= 5M", "cartpole"),
             ("cartpole training steps/s (isaacgym)", f"{cartpole['train_sps']:,.0f}", "", "cartpole")]
if summary := read("cartpole-long/summary.json"):
    wall = status["cartpole-long"]["wall_seconds"]
    rows += [(f"RPO cartpole run of {summary['total_timesteps']:,} steps: wall s (process)", f"{wall}", "< 60", "cartpole-long"),
             ("  compile s / train s", f"{summary['compile_seconds']:.1f} / {summary['train_seconds']:.1f}", "", "cartpole-long"),
             ("  final return", f"{summary['final_return_mean']:.1f}", "", "cartpole-long")]
if seeds := read("seeds.json"):
    rows.append(("10 vmapped seeds / 1 seed, wall ratio", f"{seeds['ratio']:.2f}", "< 3", "seeds"))
for name, label in (("ballbalance", "ballbalance"), ("mjx-walker", "mjx-dmc/walker-walk")):
    if result := read(f"{name}.json"):
        rows.append((f"{label} training steps/s ({result['num_envs']} envs)", f"{result['train_sps']:,.0f}", "", name))
host_env = (out / "host-walker.env").read_text().strip()
if summary := read("host-walker/summary.json"):
    rows.append((f"host-side {host_env}, one update: steps/s", f"{summary['sps']:,.0f}", "runs", "host-walker"))
if scaling := read("scaling.json"):
    for row in scaling["rows"]:
        rows.append((f"scaling: {row['placement']} on {row['devices']} device(s), {row['runs']} run(s)",
                     f"{row['sps']:,.0f}", "", "scaling"))
device = next((r["device"] for r in (read("cartpole.json"), read("seeds.json")) if r), "unknown")
versions = {"python": platform.python_version()}
for name in ("jax", "jaxlib", "mujoco", "mujoco-mjx", "brax", "playground", "envpool"):
    try:
        versions[name] = importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        pass
failed = [name for name, s in status.items() if s["exit_code"] != 0]
lines = [f"# Device check{' (CPU smoke: tiny sizes, figures mean nothing)' if smoke else ''}", "",
         f"Device: {device}. Failed or timed-out steps: {', '.join(failed) or 'none'} (logs in {out}).", "",
         "Versions: " + ", ".join(f"{name} {version}" for name, version in versions.items()) + f". Host step on {host_env}.", "",
         "| figure | value | aim | step |", "|---|---|---|---|"]
lines += [f"| {figure} | {value} | {aim} | {name} |" for figure, value, aim, name in rows]
lines += ["", "| step | exit code | wall s |", "|---|---|---|"]
lines += [f"| {name} | {s['exit_code']} | {s['wall_seconds']} |" for name, s in status.items()]
(out / "results.md").write_text("\n".join(lines) + "\n")
(out / "results.json").write_text(json.dumps({"device": device, "smoke": smoke, "versions": versions, "host_env": host_env, "status": status,
                                              "figures": [dict(zip(("figure", "value", "aim", "step"), r)) for r in rows]}, indent=2))
print("\n".join(lines))
EOF
