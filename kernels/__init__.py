"""Warp kernels and their host launchers: the only place in physcene that imports ``warp``.

This folder installs as ``physcene.kernels``. Run from the repository's root (``python -m pytest``,
``python -c``), Python also finds it as a top-level ``kernels``: a name that belongs to Hugging Face's
hub-kernels package, which transformers imports at start-up when it is installed (5.25 requires it).
Imported under that name, this module hands the import to the installed package, so the root on
``sys.path`` does not shadow it.
"""

if __name__ == "kernels":
    import importlib.machinery
    import importlib.util
    import os
    import sys

    _root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    _paths = [p for p in sys.path if os.path.abspath(p or os.curdir) != _root]
    _spec = importlib.machinery.PathFinder.find_spec("kernels", _paths)
    if _spec is None or _spec.loader is None:
        raise ImportError(f"{os.path.dirname(os.path.abspath(__file__))} is physcene.kernels (import it "
                          "under that name); no installed top-level package 'kernels' was found")
    _module = importlib.util.module_from_spec(_spec)
    sys.modules["kernels"] = _module
    _spec.loader.exec_module(_module)
