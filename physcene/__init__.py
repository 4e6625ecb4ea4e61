"""physcene: physically consistent tabletop scene generation (PhyScene3D: CTRC + PADA).

Data flows one way: text -> ``ctrc.parse`` -> ``Scene`` -> ``physics`` -> scores/gradients ->
``tto`` -> ``Scene`` -> export / eval. See docs/ and docs/design.md.
"""

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
__all__ = ["TABLE", "Scene", "SceneError", "SceneObject", "Zone", "__version__"]
