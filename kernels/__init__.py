"""Warp kernels and their host launchers: the only place in physcene that imports ``warp``.

This folder installs as ``physcene.kernels``. Run from the repository's root (``python -m pytest``,
``python -c``), Python also finds it as a top-level ``kernels``: a name that belongs to Hugging Face's
hub-kernels package, which transformers imports at start-up when it is installed (5.25 requires it).
Imported under that name, this module hands the import to the installed package, so the root on
``sys.path`` does not shadow it; where none is installed (transformers before 5.25 does not require
it), the name imports as an empty module without a version, which transformers reads as "not
installed".
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
        # No hub-kernels installed. transformers probes the name at start-up (find_spec, then its
        # version, then an import) and reads a module without a version as not installed, so the name
        # stays importable and empty: anything asked of it says what this folder is.
        _OWN = os.path.dirname(os.path.abspath(__file__))

        def __getattr__(name: str):
            raise AttributeError(f"{_OWN} is physcene.kernels (import it under that name); no installed "
                                 f"top-level package 'kernels' (Hugging Face's hub-kernels) has {name!r}")
    else:
        _module = importlib.util.module_from_spec(_spec)
        sys.modules["kernels"] = _module
        _spec.loader.exec_module(_module)
