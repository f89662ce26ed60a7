"""Import PyPI ``lerobot`` (0.4.x) next to this project's CPU torch and transformers 5, offline.

``lerobot`` is not a dependency of the project: ``scripts/install-interop.sh`` installs it without
its pins (they would replace torch, numpy and protobuf). Two things then stand in the way of
``import lerobot.policies``, and :func:`import_lerobot` handles both without touching either package:

* torchvision. ``lerobot.datasets.utils`` and ``lerobot.processor.hil_processor`` import it at
  module level, but the policies served here (e.g. TD-MPC) never call it. torchvision's PyPI wheels
  are CUDA builds that cannot be imported beside the CPU torch this project pins, so when it does
  not import, a stand-in package is registered whose every use raises :class:`TorchvisionUnavailable`
  (a policy that really needs it, such as ACT's or Diffusion's ResNet backbone, fails loudly at
  construction, naming torchvision). The libraries that probe for torchvision (transformers,
  diffusers, datasets) are imported first, so they see that it is absent.
  tests/unit/test_lerobot_export.py does the same for ``lerobot-dataset``.
* GR00T. ``lerobot/policies/__init__.py`` imports ``groot/__init__.py``, which imports GR00T's
  modeling code; one of its dataclasses subclasses transformers' ``PretrainedConfig``, which
  transformers 5 made a dataclass with defaults, so its definition raises ``TypeError``. The
  ``lerobot.policies.groot`` package is registered without running its ``__init__``: its config
  class still registers, the GR00T policy class itself is not loadable here.

``ZETTA_LEROBOT_PATH`` (a folder, e.g. one made by ``pip install --target``) is put on ``sys.path``
first when set.
"""

from __future__ import annotations

import importlib
import importlib.machinery
import importlib.util
import os
import sys
import types
from typing import Any


class LeRobotUnavailable(ImportError):
    """PyPI ``lerobot`` cannot be imported here."""


class TorchvisionUnavailable(RuntimeError):
    """Raised by every use of the torchvision stand-in."""


def _refusing_module(name: str) -> types.ModuleType:
    mod = types.ModuleType(name)
    mod.__path__ = []  # a package: its submodules import by name

    def __getattr__(attr: str) -> Any:
        if attr.startswith("__"):
            raise AttributeError(attr)

        message = (f"{name}.{attr} was used, but torchvision cannot be imported beside this torch; "
                   "this LeRobot policy type needs torchvision (serve one that does not, e.g. tdmpc)")

        def refuse(*_a: Any, **_k: Any) -> Any:
            raise TorchvisionUnavailable(message)
        if attr[:1].isupper():  # a class: modules may subclass it (lerobot's image transforms do)
            return type(attr, (), {"__init__": refuse, "__module__": name})
        return refuse

    mod.__getattr__ = __getattr__  # type: ignore[method-assign]
    return mod


#: The torchvision modules lerobot imports at module level (parents first).
_STAND_IN = ("torchvision", "torchvision.transforms", "torchvision.transforms.functional", "torchvision.transforms.v2",
             "torchvision.transforms.v2.functional", "torchvision.io", "torchvision.models", "torchvision.ops")


def _stand_in_torchvision() -> bool:
    """Register the refusing torchvision package when the real one does not import; True if done."""
    if "torchvision" in sys.modules:
        return False
    try:
        importlib.import_module("torchvision")
        return False
    except (ImportError, RuntimeError, OSError):  # RuntimeError: a CUDA build's operator registration
        for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
            del sys.modules[name]
    # Libraries that record at import whether torchvision exists: let them see that it does not.
    for probe in ("transformers.utils.import_utils", "diffusers.utils.import_utils", "datasets"):
        try:
            importlib.import_module(probe)
        except ImportError:
            pass
    for name in _STAND_IN:
        sys.modules[name] = _refusing_module(name)
        parent, _, child = name.rpartition(".")
        if parent:
            setattr(sys.modules[parent], child, sys.modules[name])
    return True


def _groot_without_init(root: str) -> None:
    name = "lerobot.policies.groot"
    if name in sys.modules:
        return
    path = os.path.join(root, "policies", "groot")
    if not os.path.isdir(path):
        return
    spec = importlib.machinery.ModuleSpec(name, None, is_package=True)
    spec.submodule_search_locations = [path]
    mod = importlib.util.module_from_spec(spec)
    mod.__path__ = [path]
    sys.modules[name] = mod


def import_lerobot() -> types.ModuleType:
    """``lerobot.policies.factory``, importable here; raises :class:`LeRobotUnavailable` naming why not."""
    extra = os.environ.get("ZETTA_LEROBOT_PATH", "").strip()
    if extra and extra not in sys.path:
        sys.path.insert(0, extra)
    if "lerobot.policies.factory" in sys.modules:
        return sys.modules["lerobot.policies.factory"]
    spec = importlib.util.find_spec("lerobot")
    if spec is None or not spec.submodule_search_locations:
        raise LeRobotUnavailable("PyPI lerobot is not installed (scripts/install-interop.sh installs it, "
                                 "or set ZETTA_LEROBOT_PATH to a folder holding it)")
    _stand_in_torchvision()
    if "lerobot.policies" not in sys.modules:
        _groot_without_init(list(spec.submodule_search_locations)[0])
    try:
        return importlib.import_module("lerobot.policies.factory")
    except ImportError as exc:
        raise LeRobotUnavailable(f"lerobot is installed but does not import: {exc} "
                                 "(scripts/install-interop.sh lists the packages it needs)") from exc
