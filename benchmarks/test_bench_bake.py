"""Bake time of one asset's 64^3 SDF grid with the Warp kernel (issue 3: <= 1 s CPU, <= 50 ms GPU).

    python -m pytest benchmarks/test_bench_bake.py --benchmark-enable -q            # CPU (+ GPU if any)
    python -m pytest benchmarks/test_bench_bake.py --benchmark-enable -q -k cuda    # GPU only

Meshes: the procedural mug, bowl, basket, teapot and plant (1-2 k triangles, the library's
typical sizes) and a 5 k-triangle icosphere, already normalised, so only the bake is timed (no
cache). With ``--benchmark-enable`` each case asserts its median against the target.
"""

from __future__ import annotations

import pytest
import trimesh

from physcene.assets import normalise_mesh, procedural_mesh, sign_method_for
from physcene.kernels.sdf_bake import bake_sdf

CASES = ["mug", "bowl", "basket", "teapot", "plant", "icosphere"]
RESOLUTION = 64


def _mesh(name):
    if name == "icosphere":
        return trimesh.creation.icosphere(subdivisions=4)
    return normalise_mesh(procedural_mesh(name))[0]


def _has_cuda() -> bool:
    import warp as wp

    return wp.get_cuda_device_count() > 0


def _run(benchmark, name, device, limit_s):
    mesh = _mesh(name)
    method = sign_method_for(mesh)
    bake_sdf(mesh.vertices, mesh.faces, RESOLUTION, sign_method=method, device=device)  # JIT + warm caches
    grid = benchmark.pedantic(
        bake_sdf,
        args=(mesh.vertices, mesh.faces, RESOLUTION),
        kwargs={"sign_method": method, "device": device},
        rounds=5,
        iterations=1,
    )
    assert grid.shape == (RESOLUTION,) * 3
    benchmark.extra_info.update(faces=len(mesh.faces), sign_method=method, device=device)
    if benchmark.enabled:
        median = benchmark.stats.stats.median
        assert median <= limit_s, f"{name}: median bake {median:.3f} s on {device} > {limit_s} s"


@pytest.mark.parametrize("name", CASES)
def test_bench_bake_cpu(benchmark, name):
    _run(benchmark, name, "cpu", 1.0)


@pytest.mark.cuda
@pytest.mark.skipif(not _has_cuda(), reason="needs a CUDA device")
@pytest.mark.parametrize("name", CASES)
def test_bench_bake_cuda(benchmark, name):
    _run(benchmark, name, "cuda:0", 0.050)
