"""Camera-model hot paths, for checking that the one formula set costs nothing.

Times, each warm (JIT excluded), best of ``--repeat``:

* ``ba-jacobian``: bundle adjustment's jitted ``vmap(jacfwd(project_full_one))`` over
  a 2,048-observation chunk with 5 distortion coefficients (``ba.problem``'s kernel);
* ``project_full``: JAX projection of 10,000 x 38 points through 7 distorted cameras;
* ``group.project``: the same through ``CameraGroup.project`` (NumPy);
* ``rodrigues-np``: ``rvec_to_rmat_numpy`` on 100,000 vectors;
* ``group.triangulate`` / ``triangulation.triangulate``: the DLT on 10,000 x 38
  undistorted points (frames/s).

To compare two trees, run it on both, alternately, in one session (timings on a
shared machine drift), e.g. ``PYTHONPATH=<old>/src python benchmarks/camera_model.py``
then ``PYTHONPATH=src python benchmarks/camera_model.py``, and again.

Run: ``.venv/bin/python benchmarks/camera_model.py [--repeat 5]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def _best(func, repeat: int) -> float:
    func()  # warm-up: compile
    best = np.inf
    for _ in range(repeat):
        start = time.perf_counter()
        func()
        best = min(best, time.perf_counter() - start)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()

    import jax

    from flylib import triangulation
    from flylib.camera import jax_model
    from flylib.camera.rig import CameraGroup, orbit_extrinsics

    rng = np.random.default_rng(0)
    azimuths = [-120, -90, -45, 0, 45, 90, 120]
    ext = [orbit_extrinsics(distance=107.463, azimuth_deg=a) for a in azimuths]
    rvecs, tvecs = np.array([e[0] for e in ext]), np.array([e[1] for e in ext])
    intrs = np.tile([22388.125, 22388.125, 480.0, 240.0], (7, 1))
    dists = np.tile([-0.05, 0.01, 1e-4, -1e-4, 0.0], (7, 1))
    rig = CameraGroup.from_arrays([str(a) for a in azimuths], rvecs, tvecs, intrs, dists)
    plain = CameraGroup.from_arrays(rig.names, rvecs, tvecs, intrs, np.zeros((7, 0)))

    def project_row(pt, row):
        return jax_model.project_full_one(pt, row[0:3], row[3:6], row[6:10], row[10:])

    def project_with_jac(pt, row):
        return project_row(pt, row), *jax.jacfwd(project_row, argnums=(0, 1))(pt, row)

    jac_kernel = jax.jit(jax.vmap(project_with_jac))
    m = 2048
    pts = rng.uniform(-1.5, 1.5, size=(m, 3))
    views = rng.integers(0, 7, size=m)
    rows = np.concatenate([rvecs[views], tvecs[views], intrs[views], dists[views]], axis=1)
    pts3d = rng.uniform(-1.5, 1.5, size=(10_000, 38, 3))
    many_rvecs = rng.normal(size=(100_000, 3))
    pts2d = plain.project(pts3d)

    timings = {
        "ba-jacobian (2,048 obs)": _best(
            lambda: jax.block_until_ready(jac_kernel(pts, rows)), args.repeat
        ),
        "project_full (JAX, 380k x 7)": _best(
            lambda: jax.block_until_ready(
                jax_model.project_full(pts3d, rvecs, tvecs, intrs, dists)
            ),
            args.repeat,
        ),
        "group.project (NumPy, 380k x 7)": _best(lambda: rig.project(pts3d), args.repeat),
        "rodrigues-np (100k)": _best(lambda: jax_model.rvec_to_rmat_numpy(many_rvecs), args.repeat),
        "group.triangulate (10k frames)": _best(lambda: plain.triangulate(pts2d), args.repeat),
        "triangulation.triangulate (10k frames)": _best(
            lambda: triangulation.triangulate(plain, pts2d), args.repeat
        ),
    }
    for name, seconds in timings.items():
        extra = f"  ({10_000 / seconds:,.0f} frames/s)" if "frames" in name else ""
        print(f"  {name:40s} {seconds * 1e3:9.3f} ms{extra}")


if __name__ == "__main__":
    main()
