"""Start-up check that every served model reads only tensors an env family can supply.

A checkpoint that declares an input no session will ever carry (a camera the family does not
have, a tensor renamed since training, a wrong image size) would otherwise fail on every
request; the worker refuses to start instead, naming the model and the tensor.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from services.common.config import ConfigError
from services.common.specs import TensorSpec, render_config

#: The smallest valid config of each family that the check knows how to build.
BASE_CONFIGS: dict[str, dict[str, Any]] = {"libero": {"suite": "libero_goal"}, "robosuite": {"env_name": "Lift"}}


def supplied_schema(family: str, specs: Sequence[TensorSpec]) -> dict[str, TensorSpec]:
    """The observation schema ``family`` gives a session created to render what ``specs`` read."""
    from services.env_worker.families import get_family

    if family not in BASE_CONFIGS:
        raise ConfigError(f"ZETTA_INPUT_CHECK_FAMILY: {family!r} is not one of {sorted(BASE_CONFIGS)}")
    cls = get_family(family)
    instance = cls(cls.canonical_config({**BASE_CONFIGS[family], **render_config(list(specs))}))
    try:
        return dict(instance.obs_schema())
    finally:
        instance.close()


def missing_inputs(specs: Sequence[TensorSpec], schema: Mapping[str, TensorSpec]) -> list[str]:
    """One line per declared input the schema lacks or declares with another dtype or shape."""
    problems = []
    for spec in specs:
        have = schema.get(spec.name)
        if have is None:
            problems.append(f"{spec.name} (not in the family's observations)")
        elif have.dtype != spec.dtype or tuple(have.shape) != tuple(spec.shape):
            problems.append(f"{spec.name} (declared {spec.dtype}{list(spec.shape)}, "
                            f"the family supplies {have.dtype}{list(have.shape)})")
    return problems


def check_models(models: Mapping[str, Any], family: str) -> None:
    """Raise ConfigError naming each model and tensor the family cannot supply."""
    errors = []
    for name, model in models.items():
        specs = list(model.input_specs())
        try:
            schema = supplied_schema(family, specs)
        except ValueError as exc:  # the family's own ConfigError: a camera it does not have, a bad size
            errors.append(f"model {name!r}: {exc}")
            continue
        errors += [f"model {name!r} reads {line}" for line in missing_inputs(specs, schema)]
    if errors:
        raise ConfigError(f"policy_worker: the {family} family cannot supply what the served models read: "
                          + "; ".join(errors))
