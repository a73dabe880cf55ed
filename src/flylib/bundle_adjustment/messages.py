"""What bundle adjustment tells the user: its warnings in plain words, the logged summary and
the result's JSON-able ``report``, built from :func:`~.adjust.bundle_adjust`'s fit."""

from __future__ import annotations

import logging
import warnings

import numpy as np

from .params import param_slices

log = logging.getLogger(__name__)


def warn_user(message: str) -> None:
    """Log ``message`` and warn it (:class:`RuntimeWarning`) at ``bundle_adjust``'s caller."""
    log.warning("bundle adjustment: %s", message)
    # stacklevel: this helper, _adjust, bundle_adjust, then bundle_adjust's caller
    warnings.warn(f"bundle adjustment: {message}", RuntimeWarning, stacklevel=4)


def log_summary(result, usable) -> None:
    """Log the fit's one-line summary (errors before and after, observations kept)."""
    active = result.inliers
    log.info(
        "bundle adjustment: median reprojection error %.2f px -> %.2f px "
        "(%d observations, %d set aside, %d round(s), %s)",
        result.initial_median_px,
        result.final_median_px,
        int(active.sum()),
        int(usable.sum() - active.sum()),
        result.rounds,
        result.message,
    )


def fit_warnings(args, fit, cam_part, dropped_rows, ratio, direction, fit_layout):
    """Camera groups sharing no point, else a weakly pinned rig; an unsettled inlier set."""
    names = list(args.cameras.names)
    warnings_out: list[str] = []
    if int(cam_part.max()) + 1 > 1:
        warnings_out.append(_parts_message(names, cam_part, dropped_rows))
    elif ratio < args.warn_ratio:
        warnings_out.append(
            _weak_message(_cameras_moving(direction, fit_layout, names), ratio, args.warn_ratio)
        )
    if not fit.stable:
        warnings_out.append(f"the inlier set did not settle within {fit.rounds} rounds")
    return warnings_out


def fit_report(
    args,
    layout,
    held,
    fit,
    n_rigid: int,
    usable,
    cam_part,
    dropped_rows: int,
    reseeded,
    unobserved,
    start_median,
    weakest: tuple[float, int],
    moved,
    initial_median: float,
    final_median: float,
    warnings_out: list[str],
) -> dict:
    """The result's JSON-able ``report``."""
    names = list(args.cameras.names)
    n_parts = int(cam_part.max()) + 1
    ratio, n_weak = weakest
    return {
        "solver": args.solver,
        "free": _free_report(layout, names, held, fit.problem, n_rigid),
        "kept_fraction": {
            n: (round(float(fit.active[v].sum() / usable[v].sum()), 4) if usable[v].any() else None)
            for v, n in enumerate(names)
        },
        "rounds": fit.rounds,
        "inliers_stable": bool(fit.stable),
        "reseeded": reseeded,
        "unobserved": unobserved,
        # cameras tied by shared points; several groups keep the starting rig's placement
        "camera_groups": [[n for n, p in zip(names, cam_part) if p == k] for k in range(n_parts)],
        "constraints_across_groups_dropped": dropped_rows,
        "start_median_px": None
        if start_median is None
        else {
            n: (None if not np.isfinite(m) else round(float(m), 2))
            for n, m in zip(names, start_median)
        },
        "weakest_direction": ratio if np.isfinite(ratio) else None,
        "moved_deg": {
            n: (round(float(d), 1) if np.isfinite(d) else None) for n, d in zip(names, moved)
        },
        "weak_directions": n_weak,
        "initial_median_px": initial_median if np.isfinite(initial_median) else None,
        "final_median_px": final_median if np.isfinite(final_median) else None,
        "warnings": warnings_out,
    }


def _free_report(layout, names, held, problem, n_rigid) -> dict:
    slices = param_slices(layout.var_index.shape[1] - 10)
    per_camera = {}
    for v, name in enumerate(names):
        free = layout.var_index[v] >= 0
        per_camera[name] = [p for p, (lo, hi) in slices.items() if hi > lo and free[lo:hi].any()]
    return {
        "camera_variables": int(layout.n_free),
        "per_camera": per_camera,
        "distortion_held_at_zero": len(held),
        "points": int(problem.n_points),
        "rigid_points": n_rigid,
        "bone_lengths": int(problem.n_len),
        "bone_rows": int(problem.n_bones),
    }


def _listed(names) -> str:
    names = list(names)
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"


def _groups(names, cam_part) -> tuple[list[str], str]:
    """``{a, b}`` per camera group of ``cam_part``, and the text naming the blind cameras."""
    groups = [
        "{" + ", ".join(n for n, p in zip(names, cam_part) if p == k) + "}"
        for k in range(int(cam_part.max()) + 1)
    ]
    blind = [n for n, p in zip(names, cam_part) if p < 0]
    blind_text = (
        f"; {_listed(blind)} {'sees' if len(blind) == 1 else 'see'} no point" if blind else ""
    )
    return groups, blind_text


def _parts_message(names, cam_part, dropped_rows: int) -> str:
    """The warning for cameras that fall into groups sharing no point, in plain words."""
    groups, blind_text = _groups(names, cam_part)
    across = (
        f"; the {dropped_rows} left/right and across-the-body length constraints that would "
        f"join them were not used (the images cannot check them)"
        if dropped_rows
        else ""
    )
    return (
        f"the rig is poorly determined: the cameras form {len(groups)} groups that see no "
        f"point in common ({_listed(groups)}{blind_text}), so the images cannot tell where "
        f"one group and the body parts it sees sit, how they are turned or how large they "
        f"are relative to the other group. Bundle adjustment refined each group on its own "
        f"and kept their relative placement as in the starting rig{across}. The 3D is only "
        f"as good as the starting rig there (e.g. left against right): give a calibration "
        f"file (config 'calibration'), or film a view that sees both sides (a front "
        f"camera seeing the legs of both sides)"
    )


def rig_report(plan, skeleton, whole=()) -> list[str]:
    """What a rig's 2D ``plan`` (a DetectionPlan; ``whole``: cameras keeping every imported point)
    gives each camera: its limbs, the camera groups sharing points, whether left and right join."""
    from ..handedness import side_groups
    from .parts import camera_parts, point_parts

    names, seen = plan.view_names, plan.filled_mask() | np.isin(plan.view_names, whole)[:, None]
    ids, at = np.arange(seen.shape[1]), plan.point_names.index
    limbed = {p for chain in skeleton.limbs.values() for p in chain}
    chains = {**skeleton.limbs, **{p: (p,) for p in plan.point_names if p not in limbed}}
    lines = [f"rig: {len(names)} camera(s), the 2D points each is planned to see:"]
    for v, name in enumerate(names):
        counts = [(k, int(seen[v, [at(p) for p in c]].sum()), len(c)) for k, c in chains.items()]
        shown = [k if n == m else f"{k} ({n} of {m} points)" for k, n, m in counts if n]
        ask = f"none (give pose2d.output_points.{name}, the pathway and channel of each point, or import its 2D)"
        lines.append(f"  {name}: {', '.join(shown) or ask}")
    groups, blind = _groups(names, camera_parts(seen, ids, ids.size))
    count = f"{len(groups)} groups that see no point in common, " if len(groups) > 1 else ""
    lines.append(f"cameras sharing points: {count}{_listed(groups) if groups else 'none'}{blind}")
    sides = side_groups(skeleton)
    if isinstance(sides, str):
        return [*lines, f"left and right: not checked, {sides}"]

    def sides_seen(mask) -> tuple[set, set]:  # the parts holding left and right leg points
        part = point_parts(mask, ids, ids.size, camera_parts(mask, ids, ids.size))
        return tuple(set(part[sides[s]]) - {-1} for s in ("left", "right"))

    left, right = sides_seen(seen)
    if not (left and right):
        unseen = [s for s, p in (("left", left), ("right", right)) if not p]
        return [*lines, f"left and right: no camera is planned to see the {_listed(unseen)} legs"]
    if not left & right:
        return [
            *lines,
            "left and right are not joined (no camera, nor chain of cameras sharing points, "
            "sees both sides): 3D left against right is only as good as the starting rig; give "
            "a calibration file (config 'calibration'), or film a view that sees the legs of "
            "both sides",
        ]
    without = [seen & (np.arange(len(names)) != v)[:, None] for v in range(len(names))]
    only = [n for n, mask in zip(names, without) if not set.intersection(*sides_seen(mask))]
    if not only:
        return [*lines, "left and right are joined by several cameras (none alone is needed)"]
    return [
        *lines,
        f"left and right are joined only by camera{'s' if len(only) > 1 else ''} "
        f"{_listed(only)}: where {'it sees' if len(only) == 1 else 'they see'} too few points "
        "of both sides, 3D left against right is only as good as the starting rig",
    ]


def moved_message(cameras, degrees) -> str:
    """The warning for cameras the fit moved far around the fly, in plain words."""
    many = len(cameras) > 1
    return (
        f"{'cameras' if many else 'camera'} {_listed(cameras)} ended "
        f"{_listed([f'{d:.0f}' for d in degrees])} degrees away (around the fly) from where "
        f"the configured rig puts {'them' if many else 'it'}: {'their' if many else 'its'} "
        f"videos or 2D may be swapped with another camera's or mislabeled. Check which "
        f"footage or 2D file belongs to which camera (config 'sources', or "
        f"pose2d.import.views) and the rig in the config; the 3D may be mirrored or "
        f"wrong where these cameras were used"
    )


def unchecked_message(cameras, degrees) -> str:
    """Why the configured rig was kept: the fit moved cameras that no held-out view checks."""
    many = len(cameras) > 1
    return (
        f"kept the configured rig: the fit moved {'cameras' if many else 'camera'} "
        f"{_listed(cameras)} {_listed([f'{d:.0f}' for d in degrees])} degrees around the fly, "
        f"but few of the points {'they see' if many else 'it sees'} are seen by two other "
        f"cameras, so no held-out view can check the move (two views of a point fit almost any "
        f"rig). For a refined rig give a calibration file (config 'calibration') or add a "
        f"camera that sees what two others see"
    )


def worse_message(start_px: float, fit_px: float) -> str:
    """Why the configured rig was kept: the fit's held-out-view error is higher."""
    return (
        f"kept the configured rig: its held-out-view error ({start_px:.1f} px median) is lower "
        f"than the adjusted rig's ({fit_px:.1f} px)"
    )


def _cameras_moving(direction, layout, names, share: float = 0.5) -> list[str]:
    """Cameras whose free parameters carry at least ``share`` of the largest component of a
    reduced-system direction (its first ``n_free`` entries are camera variables)."""
    n_free = int(layout.n_free)
    if direction.size < n_free or n_free == 0:
        return []
    size = np.abs(direction[:n_free])
    per_camera = np.array(
        [
            size[var[var >= 0]].max(initial=0.0)
            for var in layout.var_index  # (V, C) variable index or -1
        ]
    )
    if per_camera.max(initial=0.0) <= 0:
        return []
    return [n for n, s in zip(names, per_camera) if s >= share * per_camera.max()]


def _weak_message(cameras, ratio: float, warn_ratio: float) -> str:
    """The warning for a rig the images barely pin, in plain words."""
    who = (
        f"cameras {_listed(cameras)}"
        if len(cameras) > 1
        else f"camera {cameras[0]}"
        if cameras
        else "some cameras"
    )
    strength = "not at all" if ratio <= 0 else f"{ratio:.0e} of the best-pinned direction"
    return (
        f"the rig is poorly determined: {who} and the points they see can move together "
        f"with almost no change in the images (pinned {strength}, below {warn_ratio:.0e}), "
        f"usually because few body points are seen by them and another camera at once. "
        f"Check the 3D (bone lengths in 'flylib inspect'), hold their parameters fixed "
        f"(bundle_adjustment.fixed) or give a calibration file (config 'calibration')"
    )
