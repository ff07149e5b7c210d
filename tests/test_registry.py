"""The registry's static specs (what `python -m rpo_jax.envs` lists) equal those of the built
environments."""

import pytest

from rpo_jax import envs


def built_spec(name: str) -> envs.EnvSpec:
    try:
        return envs.make_env(name).spec
    except envs.MissingExtraError as error:
        pytest.skip(str(error))


@pytest.mark.parametrize(
    "name", ["cartpole", "gym/Pendulum-v1", "gym/BipedalWalker-v3", "pybullet/Ant", "dmc/walker-walk", "mjx-dmc/walker-walk"]
)
def test_static_spec_is_the_built_environments(name):
    assert envs.env_spec(name) == built_spec(name)


@pytest.mark.slow
@pytest.mark.parametrize("name", [name for name in envs.REGISTRY if name.startswith(("brax/", "pybullet/", "dmc/", "mjx-dmc/"))])
def test_static_spec_is_the_built_environments_everywhere(name):
    assert envs.env_spec(name) == built_spec(name)
