"""Every public name of the library's front door (`rpo_jax.__all__`) and of the environment
protocol (`rpo_jax.envs.protocol`) has a docstring: the API reference of the docs is built from
them, so a name without one would be an empty entry there."""

import importlib
import inspect

import rpo_jax
import rpo_jax.envs.protocol as protocol


def public_methods(cls: type) -> list[tuple[str, object]]:
    """The functions and properties a class defines itself (not inherited, not dunder)."""
    return [
        (name, value)
        for name, value in vars(cls).items()
        if not name.startswith("_") and (inspect.isfunction(value) or isinstance(value, property))
    ]


def documented_names() -> dict[str, object]:
    """label -> object for every module, class, function and method the docs must document."""
    names: dict[str, object] = {"rpo_jax": rpo_jax, "rpo_jax.envs": importlib.import_module("rpo_jax.envs")}
    exported = {name: getattr(rpo_jax, name) for name in rpo_jax.__all__}
    defined_in_protocol = {
        f"protocol.{name}": value
        for name, value in vars(protocol).items()
        if not name.startswith("_") and getattr(value, "__module__", None) == protocol.__name__
    }
    for label, value in {**exported, **defined_in_protocol}.items():
        if not (inspect.isclass(value) or inspect.isfunction(value)):
            continue  # tables such as PRESETS and ALGORITHMS: data, documented where they are declared
        names[label] = value
        names[value.__module__] = importlib.import_module(value.__module__)
        if inspect.isclass(value):
            names.update({f"{label}.{name}": method for name, method in public_methods(value)})
    return names


def test_every_public_name_has_a_docstring():
    names = documented_names()
    missing = [
        label
        for label, value in names.items()
        if not (inspect.getdoc(value.fget if isinstance(value, property) else value) or "").strip()
    ]
    assert len(names) >= 35, sorted(names)  # the walk found the names, not an empty list
    assert missing == [], f"{len(missing)} of {len(names)} public names have no docstring: {missing}"
