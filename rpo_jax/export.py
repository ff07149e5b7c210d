"""Export a trained policy for use without Python's JAX: ONNX, and plain NumPy arrays.

    python -m rpo_jax.export runs/cartpole-rpo-20261123-101500 --onnx policy.onnx --npz policy.npz

Both hold the deterministic policy of one run (`--run`, as listed in config.json) with its
observation normalisation: a raw observation in, the action that `rpo_jax.load_policy(run_dir,
run)(obs, key, deterministic=True)` takes out (the policy's location, clipped to the
environment's bounds).

The `.npz` holds float32 arrays `obs_mean`, `obs_std`, `obs_clip`, `kernel_0`, `bias_0`, ...,
`kernel_N`, `bias_N` (N + 1 dense layers, the last one the output), `action_low`, `action_high`,
`log_std` (the state-independent log-scale, for sampling) and the string `activation`
(tanh, relu, elu or silu). The forward pass, which `forward` implements:

    x = clip((obs - obs_mean) / obs_std, -obs_clip, obs_clip)
    x = activation(x @ kernel_i + bias_i)          for i in 0 .. N-1
    action = clip(x @ kernel_N + bias_N, action_low, action_high)

A run trained without observation normalisation has obs_mean 0, obs_std 1 and obs_clip inf.
`obs_std` is sqrt(var + 1e-8) of the run's running statistics, as training divides by it.

The ONNX model (opset 17) computes the same with input `obs` [batch, obs_size] float32 and
output `action` [batch, action_size]; its check needs the `onnx` extra (onnx, onnxruntime).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from rpo_jax.cli import ArgumentParser
from rpo_jax.errors import UsageError, usage_failure
from rpo_jax.rundir import PARAMS_FILE, RunDir

ACTIVATIONS = {
    "tanh": np.tanh,
    "relu": lambda x: np.maximum(x, 0),
    "elu": lambda x: np.where(x > 0, x, np.expm1(np.minimum(x, 0))),
    "silu": lambda x: x / (1 + np.exp(-x)),
}
OPSET = 17


def policy_arrays(run_dir: Path, run: int = 0) -> dict[str, np.ndarray]:
    """The arrays of the `.npz` for run `run` of `run_dir`."""
    from rpo_jax.policy import load_run

    config, spec, actor_params, stats = load_run(run_dir, run)
    mlp = actor_params["params"]["MLP_0"]
    layers = [mlp[f"Dense_{i}"] for i in range(len(mlp))]
    arrays = {f"{kind}_{i}": np.asarray(layer[kind], np.float32) for i, layer in enumerate(layers) for kind in ("kernel", "bias")}
    obs_size = arrays["kernel_0"].shape[0]
    if config.normalize_obs:
        mean, std, clip = np.asarray(stats.mean), np.sqrt(np.asarray(stats.var, np.float32) + np.float32(1e-8)), config.obs_clip
    else:
        mean, std, clip = np.zeros(obs_size), np.ones(obs_size), np.inf
    return {
        "obs_mean": np.asarray(mean, np.float32), "obs_std": np.asarray(std, np.float32), "obs_clip": np.float32(clip),
        **arrays,
        "action_low": np.asarray(spec["action_low"], np.float32), "action_high": np.asarray(spec["action_high"], np.float32),
        "log_std": np.asarray(actor_params["params"]["log_std"], np.float32), "activation": np.str_(config.activation),
    }  # fmt: skip


def forward(arrays: Any, obs: np.ndarray) -> np.ndarray:
    """The deterministic action for raw observations [..., obs_size] from the `.npz`'s arrays."""
    layers = sum(1 for name in arrays if name.startswith("kernel_"))
    activation = ACTIVATIONS[str(arrays["activation"])]
    x = np.clip((np.asarray(obs, np.float32) - arrays["obs_mean"]) / arrays["obs_std"], -arrays["obs_clip"], arrays["obs_clip"])
    for i in range(layers - 1):
        x = activation(x @ arrays[f"kernel_{i}"] + arrays[f"bias_{i}"])
    x = x @ arrays[f"kernel_{layers - 1}"] + arrays[f"bias_{layers - 1}"]
    return np.clip(x, arrays["action_low"], arrays["action_high"])


def onnx_model(arrays: dict[str, np.ndarray]) -> Any:
    """The forward pass as an ONNX model built from the arrays."""
    from onnx import TensorProto, helper, numpy_helper

    layers = sum(1 for name in arrays if name.startswith("kernel_"))
    constants = {name: value for name, value in arrays.items() if name not in ("activation", "log_std")}
    nodes = [
        helper.make_node("Sub", ["obs", "obs_mean"], ["centred"]),
        helper.make_node("Div", ["centred", "obs_std"], ["scaled"]),
        helper.make_node("Neg", ["obs_clip"], ["minus_obs_clip"]),
        helper.make_node("Max", ["scaled", "minus_obs_clip"], ["floored"]),
        helper.make_node("Min", ["floored", "obs_clip"], ["x_0"]),
    ]
    for i in range(layers):
        nodes += [
            helper.make_node("MatMul", [f"x_{i}", f"kernel_{i}"], [f"product_{i}"]),
            helper.make_node("Add", [f"product_{i}", f"bias_{i}"], [f"pre_{i}" if i < layers - 1 else "location"]),
        ]
        if i < layers - 1:
            nodes += activation_nodes(str(arrays["activation"]), f"pre_{i}", f"x_{i + 1}")
    nodes += [
        helper.make_node("Max", ["location", "action_low"], ["raised"]),
        helper.make_node("Min", ["raised", "action_high"], ["action"]),
    ]
    obs_size, action_size = arrays["kernel_0"].shape[0], arrays[f"kernel_{layers - 1}"].shape[1]
    graph = helper.make_graph(
        nodes, "rpo_jax_policy",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["batch", obs_size])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", action_size])],
        initializer=[numpy_helper.from_array(np.asarray(value, np.float32), name) for name, value in constants.items()],
    )  # fmt: skip
    # IR version 9 with opset 17: what onnxruntime releases since 1.15 load.
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], ir_version=9, producer_name="rpo_jax")


def activation_nodes(activation: str, x: str, out: str) -> list[Any]:
    from onnx import helper

    if activation == "silu":
        return [helper.make_node("Sigmoid", [x], [f"{out}_gate"]), helper.make_node("Mul", [x, f"{out}_gate"], [out])]
    operator = {"tanh": "Tanh", "relu": "Relu", "elu": "Elu"}[activation]
    return [helper.make_node(operator, [x], [out], **({"alpha": 1.0} if activation == "elu" else {}))]


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="python -m rpo_jax.export", description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a directory written by rpo_jax.train")
    parser.add_argument("--run", type=int, default=0, help="which of the directory's runs (index in config.json)")
    parser.add_argument("--onnx", type=Path, metavar="OUT.onnx", help="write the policy as an ONNX model (the onnx extra)")
    parser.add_argument("--npz", type=Path, metavar="OUT.npz", help="write the policy's arrays for NumPy")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        run_dir = RunDir(args.run_dir)
        if not run_dir.has_params():
            raise UsageError(f"{args.run_dir} has no {PARAMS_FILE}; give the directory of a finished rpo_jax.train run")
        if not (args.onnx or args.npz):
            raise UsageError("give --onnx OUT.onnx, --npz OUT.npz or both")
        for path in filter(None, (args.onnx, args.npz)):
            if path.exists():
                raise UsageError(f"{path} already exists; choose a new file")
        runs = len(run_dir.read_config()["runs"])
        if not 0 <= args.run < runs:
            raise UsageError(f"--run must be in [0, {runs}), got {args.run}")
        arrays = policy_arrays(args.run_dir, args.run)
        if args.onnx:
            try:
                import onnx
            except ImportError:
                raise UsageError("--onnx needs the onnx extra: pip install -e '.[onnx]'") from None
            onnx.save(onnx_model(arrays), args.onnx)
            print(f"onnx: {args.onnx}")
        if args.npz:
            with open(args.npz, "xb") as file:  # never over a file that appeared meanwhile
                np.savez(file, **arrays)
            print(f"npz: {args.npz}")
    except UsageError as error:
        return usage_failure(error)
    return 0


if __name__ == "__main__":
    sys.exit(main())
