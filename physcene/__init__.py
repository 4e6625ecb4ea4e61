"""physcene: physically consistent tabletop scene generation (PhyScene3D: CTRC + PADA).

Data flows one way: text -> ``ctrc.parse`` -> ``Scene`` -> ``physics`` -> scores/gradients ->
``tto`` -> ``Scene`` -> export / eval. See docs/design.md.

The public API (docs/generate.md)::

    import physcene
    result = physcene.generate("a desk with a laptop, two mugs and a pen in the pen holder")
    scene = result[0].scene
    report = physcene.check(scene)              # pairs by id, floating ids, table penetration
    fixed, repair_report = physcene.repair(scene)
    physcene.render(fixed, "desk.png")
    physcene.export(fixed, "out/", "mjcf")

``load_layout``, ``save_layout``, ``check``, ``repair``, ``reward``, ``render`` and ``export`` live in
:mod:`physcene.api`, ``generate`` in :mod:`physcene.generation`; they load on first use so that
``import physcene`` (and every ``physcene`` command's start-up) stays free of torch and Warp.
"""

import importlib as _importlib
import sys as _sys
import types as _types
from pathlib import Path as _Path

from physcene.scene import TABLE, Scene, SceneError, SceneObject, Zone

# In a source checkout, ``kernels/``, ``train/``, ``eval/`` and ``configs/`` sit beside this package
# and are installed as ``physcene.kernels`` etc. (pyproject's package-dir). When this checkout is
# imported straight from sys.path (``python -m physcene.cli`` in the repo root, PYTHONPATH=checkout,
# a second git worktree) the editable install's mapping may point at another tree or none, so the
# sub-packages are looked up beside the package too: the checkout's own code, never another's.
_CHECKOUT = _Path(__file__).resolve().parent.parent
if (_CHECKOUT / "pyproject.toml").is_file() and (_CHECKOUT / "kernels" / "penetration.py").is_file():
    __path__.append(str(_CHECKOUT))  # noqa: F821 (set by the import system)


__version__ = "0.1.0"

# Public functions -> the module that defines them (loaded on first access, PEP 562).
_LAZY = {"load_layout": "physcene.api", "save_layout": "physcene.api", "check": "physcene.api",
         "repair": "physcene.api", "render": "physcene.api", "generate": "physcene.generation"}
# ``physcene.reward`` and ``physcene.export`` are both stage packages (``from physcene.reward import
# PhysicsReward``) and API functions (``physcene.reward(completions)``): the import system binds a
# submodule to its parent's attribute on first import, which would replace a plain function, so the
# submodule itself is made callable (a ModuleType subclass, as Python's data model allows).
_CALLABLE_SUBMODULES = ("reward", "export")

__all__ = ["TABLE", "Scene", "SceneError", "SceneObject", "Zone", "__version__", "check", "export",
           "generate", "load_layout", "render", "repair", "reward", "save_layout"]


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(_importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'physcene' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY) | set(_CALLABLE_SUBMODULES))


class _CallableModule(_types.ModuleType):
    """A stage module that, called, runs the :mod:`physcene.api` function of its name."""

    def __call__(self, *args, **kwargs):
        api = _importlib.import_module("physcene.api")
        return getattr(api, self.__name__.rpartition(".")[2])(*args, **kwargs)


def _callable_submodule(name: str) -> property:
    key = f"_submodule_{name}"

    def get(package):
        if key not in package.__dict__:
            _importlib.import_module(f"physcene.{name}")  # the import system calls ``put``
        return package.__dict__[key]

    def put(package, module):
        if type(module) is _types.ModuleType:
            module.__class__ = _CallableModule
        package.__dict__[key] = module

    return property(get, put, doc=f"physcene.{name}: the stage package, callable as physcene.api.{name}")


class _Package(_types.ModuleType):
    reward = _callable_submodule("reward")
    export = _callable_submodule("export")


_sys.modules[__name__].__class__ = _Package
