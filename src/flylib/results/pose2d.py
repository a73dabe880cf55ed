"""The pose2d stage's output, from the detector or another tool's files: :class:`Pose2dData`.

The artifact ``stages/pose2d.h5`` holds ``skeleton/`` and ``pose2d/{points, conf}`` with the view
names and raw image sizes as JSON attributes; no rig (editing the rig must not re-run detection).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import ResultsError
from ..paths import atomic_path
from ..skeleton import Skeleton
from .candidates import read_candidates, write_candidates
from .datasets import json_attrs, read_dataset, read_json_attrs, read_strings, write_array
from .groups import write_skeleton
from .hdf5 import create_file, new_meta, read_checked

if TYPE_CHECKING:  # pragma: no cover
    from jaxtyping import Float


@dataclass
class Pose2dData:
    """The pose2d stage's output, from the detector or imported from another tool: ``pts2d`` in
    raw-frame pixels (NaN = missing), ``conf``, ``view_names`` (the V axis, config order),
    ``image_sizes`` (``view -> (height, width)`` of the raw footage) and the top-K peaks
    (:class:`~flylib.pictorial.Candidates`) when pictorial structures is on, else ``None``."""

    pts2d: Float[np.ndarray, "V T P 2"]
    conf: Float[np.ndarray, "V T P"]
    view_names: list[str]
    image_sizes: dict[str, tuple[int, int]]
    candidates: Any = None

    def __post_init__(self) -> None:
        self.pts2d = np.asarray(self.pts2d, dtype=np.float64)
        self.conf = np.asarray(self.conf, dtype=np.float64)
        self.view_names = [str(v) for v in self.view_names]
        self.image_sizes = {str(k): (int(v[0]), int(v[1])) for k, v in self.image_sizes.items()}
        if self.pts2d.ndim != 4 or self.pts2d.shape[-1] != 2:
            raise ValueError(f"pts2d must be (V, T, P, 2), got shape {self.pts2d.shape}")
        if self.conf.shape != self.pts2d.shape[:3]:
            raise ValueError(f"conf must have shape {self.pts2d.shape[:3]}, got {self.conf.shape}")
        if len(self.view_names) != self.pts2d.shape[0]:
            raise ValueError(f"{len(self.view_names)} view names for {self.pts2d.shape[0]} views")
        if self.candidates is not None:
            v, t, p = self.pts2d.shape[:3]
            xy, score = np.shape(self.candidates.xy), np.shape(self.candidates.score)
            if len(xy) != 5 or xy[:3] != (v, t, p) or xy[4] != 2 or score != xy[:4]:
                raise ValueError(
                    f"candidates must be xy (V, T, P, K, 2) / score (V, T, P, K), got {xy} / {score}"
                )

    def save(
        self, path: str | Path, skeleton: Skeleton, meta: Mapping[str, Any] | None = None
    ) -> None:
        """Write ``skeleton/`` (the P axis) and ``pose2d/`` to ``path`` atomically; ``meta``: extra
        entries for the file's meta JSON (e.g. its params hash)."""
        if skeleton.n_points != self.pts2d.shape[2]:
            raise ValueError(
                f"pts2d has {self.pts2d.shape[2]} points but the skeleton has {skeleton.n_points}"
            )
        with atomic_path(path) as tmp, create_file(tmp) as f:
            f.attrs["meta"] = json.dumps(new_meta("pose2d", meta))
            write_skeleton(f.create_group("skeleton"), skeleton)
            group = f.create_group("pose2d")
            write_array(group, "points", self.pts2d)
            write_array(group, "conf", self.conf)
            json_attrs(
                group,
                {
                    "view_names": self.view_names,
                    "image_sizes": {k: list(v) for k, v in self.image_sizes.items()},
                },
            )
            if self.candidates is not None:
                write_candidates(group.create_group("candidates"), self.candidates)

    @classmethod
    def load(cls, path: str | Path) -> Pose2dData:
        """Read a pose2d artifact or results file; missing, stale or no group: a ResultsError."""
        rerun = "re-run the pose2d stage"
        with read_checked(path, rerun) as f:
            if "pose2d/points" not in f:
                raise ResultsError(f"{path}: has no pose2d group; {rerun}")
            group = f["pose2d"]
            attrs = read_json_attrs(group)
            candidates = read_candidates(group) if "candidates" in group else None
            views = attrs.get("view_names")
            if views is None and "cameras" in group:
                views = read_strings(group["cameras/names"])
            return cls(
                pts2d=read_dataset(group["points"]),
                conf=read_dataset(group["conf"])
                if "conf" in group
                else np.ones(group["points"].shape[:3]),
                view_names=list(views or []),
                image_sizes={k: tuple(v) for k, v in (attrs.get("image_sizes") or {}).items()},
                candidates=candidates,
            )


def read_image_sizes(path: str | Path) -> dict[str, tuple[int, int]]:
    """``view -> (height, width)`` of a pose2d artifact or results file, without reading its
    arrays (a ResultsError as :meth:`Pose2dData.load`)."""
    with read_checked(path, "re-run the pose2d stage") as f:
        if "pose2d" not in f:
            raise ResultsError(f"{path}: has no pose2d group; re-run the pose2d stage")
        sizes = read_json_attrs(f["pose2d"]).get("image_sizes") or {}
        return {str(k): (int(v[0]), int(v[1])) for k, v in sizes.items()}
