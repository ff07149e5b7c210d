"""Export a trained policy for use without Python's JAX: ONNX, and plain NumPy arrays.

    python -m rpo_jax.export runs/cartpole-rpo-20261123-101500 --onnx policy.onnx --npz policy.npz

Both hold the deterministic policy of one run (`--run`, as listed in config.json) with its
observation normalisation: a raw observation in, the action that `rpo_jax.load_policy(run_dir,
run)(obs, key, deterministic=True)` takes out (the policy's location, clipped to the
environment's bounds).

The `.npz` holds float32 arrays `obs_mean`, `obs_std`, `obs_clip`, `kernel_0`, `bias_0`, ...,
`kernel_N`, `bias_N` (N + 1 dense layers, the last one the output), `action_low`, `action_high`,
`log_std` (the state-independent log of the distribution's scale; tanh-normal's scale is the
network's: `scale_kernel` and `scale_bias` instead), the string `activation` (tanh, relu, elu or
silu) and the string `distribution` (gaussian, laplace, gumbel or tanh-normal). The forward pass,
which `forward` implements:

    x = clip((obs - obs_mean) / obs_std, -obs_clip, obs_clip)
    x = activation(x @ kernel_i + bias_i)          for i in 0 .. N-1
    location = x @ kernel_N + bias_N
    action = clip(location, action_low, action_high)

and for tanh-normal, the location squashed onto the bounds:

    action = clip(c + h * tanh(location), action_low, action_high)   c, h = (high + low) / 2, (high - low) / 2

The stochastic policy, which `sample` implements, draws each action dimension independently
from `distribution` with that location and the scale exp(log_std), then clips it the same way:

    gaussian: location + scale * normal()      scale is the standard deviation (numpy: rng.normal(location, scale))
    laplace:  location + scale * laplace()     scale b, the standard deviation sqrt(2) b (rng.laplace(location, scale))
    gumbel:   location + scale * gumbel()      the max-Gumbel, mean location + 0.5772 scale (rng.gumbel(location, scale))
    tanh-normal: c + h * tanh(location + scale * normal()), scale = softplus(x @ scale_kernel + scale_bias) + 0.001

so `log_std` is a standard deviation's log for the Gaussian only. The deterministic action is the
location for each: the Gaussian's and Laplace's mean, the Gumbel's mode (tanh-normal: the squashed
Gaussian mean, as Brax's policies act).

A run trained without observation normalisation has obs_mean 0, obs_std 1 and obs_clip inf.
Where the observation has named parts (a robot's `state` for the policy, `privileged_state` for
the critic), `obs` is the policy's part alone: the numbers the robot itself measures.
`obs_std` is sqrt(var + 1e-8) of the run's running statistics, as training divides by it.

The ONNX model (opset 17) computes the same with input `obs` [batch, obs_size] float32 and
output `action` [batch, action_size]; its metadata (`metadata_props`) hold `distribution` and
`log_std` (a JSON list; none for tanh-normal, whose scale the ONNX model does not compute) for
sampling as above. Its check needs the `onnx` extra (onnx, onnxruntime).

Both files are written whole or not at all: through temporary files, published only when both
are written, never over an existing file.
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import sys
from pathlib import Path
from typing import Annotated, Any, Sequence

import numpy as np
import tyro

from rpo_jax.errors import UsageError, command_failures
from rpo_jax.config import MIN_SCALE, TANH_NORMAL
from rpo_jax.run.directory import RunDir, check_new_file
from rpo_jax.run.options import TrainedRun, parse

ACTIVATIONS = {
    "tanh": np.tanh,
    "relu": lambda x: np.maximum(x, 0),
    "elu": lambda x: np.where(x > 0, x, np.expm1(np.minimum(x, 0))),
    "silu": lambda x: x / (1 + np.exp(-x)),
}
# How each distribution's sample is drawn with NumPy: location and scale in, same shape out.
SAMPLERS = {
    "gaussian": lambda rng, location, scale: rng.normal(location, scale),
    "laplace": lambda rng, location, scale: rng.laplace(location, scale),
    "gumbel": lambda rng, location, scale: rng.gumbel(location, scale),
}
OPSET = 17


def policy_arrays(run_dir: Path, run: int | None = None) -> dict[str, np.ndarray]:
    """The arrays of the `.npz` for run `run` of `run_dir` (None: as `rpo_jax.load_policy`'s)."""
    from rpo_jax.acting import part_statistics
    from rpo_jax.envs.protocol import EnvSpec
    from rpo_jax.run.saved_policy import load_run

    config, record, actor_params, stats = load_run(run_dir, run)
    spec = EnvSpec.from_record(record)
    stats = part_statistics(stats, spec.part(spec.policy_obs_key))  # the policy's observation alone
    mlp = actor_params["params"]["MLP_0"]
    layers = [mlp[f"Dense_{i}"] for i in range(len(mlp))]
    arrays = {f"{kind}_{i}": np.asarray(layer[kind], np.float32) for i, layer in enumerate(layers) for kind in ("kernel", "bias")}
    if config.dist == TANH_NORMAL:  # the last layer gives the location, then the scale's input
        last, size = len(layers) - 1, spec.action_size
        for kind in ("kernel", "bias"):
            both = arrays[f"{kind}_{last}"]
            arrays[f"{kind}_{last}"], arrays[f"scale_{kind}"] = both[..., :size], both[..., size:]
        scale = {}
    else:
        scale = {"log_std": np.asarray(actor_params["params"]["log_std"], np.float32)}
    obs_size = arrays["kernel_0"].shape[0]
    if config.normalize_obs:
        mean, std, clip = np.asarray(stats.mean), np.asarray(stats.std), config.obs_clip
    else:
        mean, std, clip = np.zeros(obs_size), np.ones(obs_size), np.inf
    return {
        "obs_mean": np.asarray(mean, np.float32), "obs_std": np.asarray(std, np.float32), "obs_clip": np.float32(clip),
        **arrays,
        "action_low": np.asarray(spec.action_low, np.float32), "action_high": np.asarray(spec.action_high, np.float32),
        **scale, "activation": np.str_(config.activation), "distribution": np.str_(config.dist),
    }  # fmt: skip


def forward(arrays: Any, obs: np.ndarray) -> np.ndarray:
    """The deterministic action for raw observations [..., obs_size] from the `.npz`'s arrays."""
    return bounded(arrays, location(arrays, hidden(arrays, obs)))


def sample(arrays: Any, obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A stochastic action for raw observations [..., obs_size], as the policy draws it: from the
    `.npz`'s `distribution` at the location with its scale, squashed (tanh-normal) and clipped to the bounds."""
    features = hidden(arrays, obs)
    kind = str(arrays["distribution"])
    if kind == TANH_NORMAL:
        pre_softplus = np.asarray(features @ arrays["scale_kernel"] + arrays["scale_bias"], np.float64)
        scale = np.logaddexp(0.0, pre_softplus) + MIN_SCALE
        draw = SAMPLERS["gaussian"](rng, location(arrays, features), scale)
    else:
        draw = SAMPLERS[kind](rng, location(arrays, features), np.exp(np.asarray(arrays["log_std"], np.float64)))
    return bounded(arrays, np.asarray(draw, np.float32))


def hidden(arrays: Any, obs: np.ndarray) -> np.ndarray:
    """The last hidden layer's features for raw observations [..., obs_size]."""
    layers = sum(1 for name in arrays if name.startswith("kernel_"))
    activation = ACTIVATIONS[str(arrays["activation"])]
    x = np.clip((np.asarray(obs, np.float32) - arrays["obs_mean"]) / arrays["obs_std"], -arrays["obs_clip"], arrays["obs_clip"])
    for i in range(layers - 1):
        x = activation(x @ arrays[f"kernel_{i}"] + arrays[f"bias_{i}"])
    return x


def location(arrays: Any, features: np.ndarray) -> np.ndarray:
    """The policy's location (before squashing and clipping) from the last hidden features."""
    layers = sum(1 for name in arrays if name.startswith("kernel_"))
    return features @ arrays[f"kernel_{layers - 1}"] + arrays[f"bias_{layers - 1}"]


def bounded(arrays: Any, sample: np.ndarray) -> np.ndarray:
    """A sample (or the location) as the environment's action: squashed for tanh-normal, clipped."""
    low, high = arrays["action_low"], arrays["action_high"]
    if str(arrays["distribution"]) == TANH_NORMAL:
        sample = (high + low) / 2 + (high - low) / 2 * np.tanh(sample)
    return np.clip(sample, low, high)


def onnx_model(arrays: dict[str, np.ndarray]) -> Any:
    """The forward pass as an ONNX model built from the arrays."""
    from onnx import TensorProto, helper, numpy_helper

    layers = sum(1 for name in arrays if name.startswith("kernel_"))
    squashed = str(arrays["distribution"]) == TANH_NORMAL
    metadata = ("activation", "log_std", "distribution", "scale_kernel", "scale_bias")
    constants = {name: value for name, value in arrays.items() if name not in metadata}
    if squashed:
        low, high = (np.asarray(arrays[name], np.float32) for name in ("action_low", "action_high"))
        constants |= {"action_centre": (high + low) / 2, "action_half_width": (high - low) / 2}
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
    if squashed:
        nodes += [
            helper.make_node("Tanh", ["location"], ["tanh_location"]),
            helper.make_node("Mul", ["tanh_location", "action_half_width"], ["half_widths"]),
            helper.make_node("Add", ["half_widths", "action_centre"], ["squashed"]),
        ]
    nodes += [
        helper.make_node("Max", ["squashed" if squashed else "location", "action_low"], ["raised"]),
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
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], ir_version=9, producer_name="rpo_jax")
    sampling = {"distribution": str(arrays["distribution"])}
    if not squashed:
        sampling["log_std"] = json.dumps(np.asarray(arrays["log_std"]).tolist())
    helper.set_model_props(model, sampling)
    return model


def activation_nodes(activation: str, x: str, out: str) -> list[Any]:
    from onnx import helper

    if activation == "silu":
        return [helper.make_node("Sigmoid", [x], [f"{out}_gate"]), helper.make_node("Mul", [x, f"{out}_gate"], [out])]
    operator = {"tanh": "Tanh", "relu": "Relu", "elu": "Elu"}[activation]
    return [helper.make_node(operator, [x], [out], **({"alpha": 1.0} if activation == "elu" else {}))]


@dataclasses.dataclass(frozen=True)
class ExportArgs:
    """Export a trained policy for use without Python's JAX: one run's deterministic policy with its
    observation normalisation, as an ONNX model and as plain NumPy arrays."""

    trained: tyro.conf.OmitArgPrefixes[TrainedRun]
    onnx: Annotated[Path | None, tyro.conf.arg(metavar="OUT.onnx")] = None
    """write the policy as an ONNX model (the onnx extra)"""
    npz: Annotated[Path | None, tyro.conf.arg(metavar="OUT.npz")] = None
    """write the policy's arrays for NumPy"""


def main(argv: Sequence[str] | None = None) -> int:
    """The command line: exit code 0, or 2 for bad input."""
    with command_failures() as exit:
        args = parse(ExportArgs, sys.argv[1:] if argv is None else argv, None, "python -m rpo_jax.export")
        _, run = RunDir(args.trained.run_dir).trained_run(args.trained.run)
        outputs = {"--onnx": args.onnx, "--npz": args.npz}
        check_outputs({flag: path for flag, path in outputs.items() if path is not None})
        arrays = policy_arrays(args.trained.run_dir, run)
        contents = {}
        if args.onnx:
            contents[args.onnx] = onnx_bytes(arrays)
        if args.npz:
            npz = io.BytesIO()
            np.savez(npz, **arrays)
            contents[args.npz] = npz.getvalue()
        write_new_files(contents)
        for flag, path in outputs.items():
            if path is not None:
                print(f"{flag[2:]}: {path}")
    return exit.code


def check_outputs(outputs: dict[str, Path]) -> None:
    """Refuses, before any work, output files that cannot be written new: none given, one path
    given twice, an existing file, a missing or unwritable directory."""
    if not outputs:
        raise UsageError("give --onnx OUT.onnx, --npz OUT.npz or both")
    if len({path.absolute() for path in outputs.values()}) < len(outputs):
        raise UsageError(f"--onnx and --npz are the same file {outputs['--onnx']}; give each its own")
    for flag, path in outputs.items():
        check_new_file(flag, path)


def onnx_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    try:
        import onnx  # noqa: F401
    except ImportError:
        raise UsageError("--onnx needs the onnx extra: pip install '.[onnx]'") from None
    return onnx_model(arrays).SerializeToString()


def write_new_files(contents: dict[Path, bytes]) -> None:
    """Writes every file or none: each to a temporary file beside it, then all linked into place,
    never over a file that appeared meanwhile (UsageError; the ones already placed removed). A
    failed write (a full disk) is an OSError naming the file it was for."""
    temporary = {path: path.with_name(f".{path.name}.{os.getpid()}.tmp") for path in contents}
    placed: list[Path] = []
    try:
        for path, data in contents.items():
            try:
                temporary[path].write_bytes(data)
            except OSError as error:
                raise OSError(error.errno, error.strerror, str(path)) from None
        for path in contents:
            try:
                os.link(temporary[path], path)  # unlike a rename, fails where the file exists
            except FileExistsError:
                raise UsageError(f"{path} appeared while exporting; nothing was written, choose a new file") from None
            placed.append(path)
    except BaseException:
        for path in placed:
            path.unlink()
        raise
    finally:
        for tmp in temporary.values():
            tmp.unlink(missing_ok=True)


if __name__ == "__main__":
    sys.exit(main())
