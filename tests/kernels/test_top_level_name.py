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
        assert done.returncode == 0, done.stderr
        assert Path(done.stdout.split()[0]).resolve() == ROOT / "kernels" / "__init__.py"


def test_transformers_imports_from_the_root():
    done = _run_in_root("import transformers.integrations.hub_kernels, physcene.kernels; print('ok')")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "ok"


def test_without_hub_kernels_transformers_reads_the_name_as_not_installed(tmp_path):
    """A machine whose transformers does not require hub-kernels (5.17 on the GPU hosts) and lacks it:
    from the root, transformers' start-up probe finds the folder as ``kernels``, imports it, reads no
    version and goes on; the empty name then refuses what is asked of it, naming this folder. The
    machine is made by leaving hub-kernels out of a copy of site-packages (links, ``python -S``)."""
    import os
    import site

    for packages in site.getsitepackages():
        for entry in Path(packages).iterdir():
            hub = entry.name == "kernels" or entry.name.startswith("kernels-")
            if not hub and entry.suffix != ".pth" and not (tmp_path / entry.name).exists():
                (tmp_path / entry.name).symlink_to(entry)
    code = ("import transformers.integrations.hub_kernels, physcene.kernels, kernels\n"
            "from transformers.utils.import_utils import is_kernels_available\n"
            "print(is_kernels_available())\n"
            "try:\n    kernels.get_kernel\nexcept AttributeError as e:\n    print(e)\n")
    path = os.pathsep.join([str(ROOT), str(tmp_path)])
    done = subprocess.run([sys.executable, "-S", "-c", code], cwd=ROOT, capture_output=True, text=True,
                          timeout=300, env=dict(os.environ, PYTHONPATH=path))
    assert done.returncode == 0, done.stderr
    available, refusal = done.stdout.strip().splitlines()
    assert available == "False"
    assert "is physcene.kernels" in refusal and "'get_kernel'" in refusal
