"""Run from the repository's root, the ``kernels/`` folder must not shadow Hugging Face's ``kernels``
package, which transformers imports at start-up when it is installed."""

import importlib.metadata
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _run_in_root(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)


def _hub_kernels_installed() -> bool:
    try:
        importlib.metadata.version("kernels")
    except importlib.metadata.PackageNotFoundError:
        return False
    return True


def test_the_top_level_name_kernels_is_the_installed_package_from_the_root():
    done = _run_in_root("import kernels, physcene.kernels as own; "
                        "print(kernels.__file__); print(own.__file__)")
    if _hub_kernels_installed():
        assert done.returncode == 0, done.stderr
        hub, own = done.stdout.split()
        assert not Path(hub).resolve().is_relative_to(ROOT)
        assert Path(own).resolve() == ROOT / "kernels" / "__init__.py"
    else:
        assert done.returncode != 0
        assert "is physcene.kernels" in done.stderr


def test_transformers_imports_from_the_root():
    done = _run_in_root("import transformers.integrations.hub_kernels, physcene.kernels; print('ok')")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "ok"
