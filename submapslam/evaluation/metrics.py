"""Trajectory error metrics on numpy arrays: association, alignment, ATE, RPE.

Everything takes :class:`~submapslam.trajectory.Trajectory` objects (timestamps + poses) and
returns plain dicts of floats; no files, no plots.
"""

from __future__ import annotations

from enum import StrEnum

import numpy as np

from ..errors import ConfigError, SubmapSlamError
from ..geometry import inverse, rotation_angle
from ..trajectory import Trajectory, nearest_stamps


def _unknown(what: str, value: object, choices: type[StrEnum]) -> ConfigError:
    return ConfigError(f"unknown {what} {value!r}: use one of {', '.join(c.value for c in choices)}")


class Alignment(StrEnum):
    """How an estimate is aligned to the reference before its error is measured (Umeyama):
    ``se3`` rigid, ``sim3`` rigid and scale, ``se2`` rigid about z only (planar), ``none``.

    ``Alignment(value)`` accepts the strings; any other value is a :class:`ConfigError`.
    """

    SE3 = "se3"
    SIM3 = "sim3"
    SE2 = "se2"
    NONE = "none"

    @classmethod
    def _missing_(cls, value: object) -> Alignment:
        raise _unknown("alignment", value, cls)


class DeltaUnit(StrEnum):
    """What the RPE's ``delta`` counts: ``frames`` (matched poses) or ``meters`` of reference path."""

    FRAMES = "frames"
    METERS = "meters"

    @classmethod
    def _missing_(cls, value: object) -> DeltaUnit:
        raise _unknown("RPE unit", value, cls)


AlignMode = Alignment | str  # an Alignment or its value


def associate(est: Trajectory, ref: Trajectory, max_diff: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Match each reference stamp to the nearest estimate stamp within ``max_diff`` seconds.

    Returns index arrays ``(i_est, i_ref)`` of equal length, one-to-one, in reference order.
    """
    order = np.argsort(est.timestamps)
    ts = est.timestamps[order]
    k = np.clip(np.searchsorted(ts, ref.timestamps), 1, max(len(ts) - 1, 1))
    if len(ts) == 1:
        k = np.zeros(len(ref.timestamps), dtype=int)
        best = k
    else:
        left = np.abs(ts[k - 1] - ref.timestamps)
        right = np.abs(ts[k] - ref.timestamps)
        best = np.where(left <= right, k - 1, k)
    ok = np.abs(ts[best] - ref.timestamps) <= max_diff
    i_est, i_ref = order[best[ok]], np.nonzero(ok)[0]
    _, first = np.unique(i_est, return_index=True)  # one-to-one
    i_est, i_ref = i_est[np.sort(first)], i_ref[np.sort(first)]
    if len(i_est) == 0:
        raise SubmapSlamError(
            f"no timestamps match within {max_diff} s (estimate {est.timestamps[0]:.3f}..{est.timestamps[-1]:.3f}, "
            f"reference {ref.timestamps[0]:.3f}..{ref.timestamps[-1]:.3f})"
        )
    return i_est, i_ref


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = False, planar: bool = False) -> tuple[np.ndarray, float]:
    """Least-squares ``T, s`` with ``dst ~ s * R @ src + t`` for ``(N, 3)`` point sets.

    ``planar`` restricts the rotation to yaw (and ignores z in the fit).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    d = 2 if planar else 3
    a, b = src[:, :d], dst[:, :d]
    mu_a, mu_b = a.mean(0), b.mean(0)
    A, B = a - mu_a, b - mu_b
    H = B.T @ A / len(a)
    U, S, Vt = np.linalg.svd(H)
    D = np.eye(d)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[-1, -1] = -1
    R = U @ D @ Vt
    var_a = (A**2).sum() / len(a)
    s = float(np.trace(np.diag(S) @ D) / var_a) if with_scale and var_a > 0 else 1.0
    t = mu_b - s * R @ mu_a
    T = np.eye(4)
    T[:d, :d] = R
    T[:d, 3] = t
    if planar:
        T[2, 3] = float(np.mean(dst[:, 2] - s * src[:, 2]))
    return T, s


def align(est: Trajectory, ref: Trajectory, mode: AlignMode = Alignment.SE3) -> tuple[np.ndarray, float]:
    """Transform (and scale) that best maps the associated ``est`` positions onto ``ref``.

    ``mode`` is an :class:`Alignment` (or its string); returns ``(T (4, 4), scale)``.
    """
    mode = Alignment(mode)
    if mode == Alignment.NONE:
        return np.eye(4), 1.0
    if len(est) < 3:
        raise SubmapSlamError(f"alignment needs at least 3 matched poses, got {len(est)}")
    return umeyama(est.positions, ref.positions, with_scale=(mode == Alignment.SIM3), planar=(mode == Alignment.SE2))


def _apply(T: np.ndarray, s: float, poses: np.ndarray) -> np.ndarray:
    out = poses.copy()
    out[:, :3, 3] = s * poses[:, :3, 3]
    return T @ out


def _stats(errors: np.ndarray) -> dict:
    return {
        "rmse": float(np.sqrt(np.mean(errors**2))), "mean": float(np.mean(errors)),
        "median": float(np.median(errors)), "std": float(np.std(errors)),
        "max": float(np.max(errors)), "n": int(len(errors)),
    }


def ate(est: Trajectory, ref: Trajectory, align: AlignMode = Alignment.SE3, max_diff: float = 0.02) -> dict:
    """Absolute trajectory error (translation) after alignment: rmse/mean/median/std/max/n [m].

    ``align`` is an :class:`Alignment` (or its string). Also returns ``errors`` (per matched
    pose), ``rotation_rmse_deg`` and ``scale``.
    """
    align = Alignment(align)
    i_e, i_r = associate(est, ref, max_diff)
    e, r = est.subset(i_e), ref.subset(i_r)
    T, s = globals()["align"](e, r, align)
    aligned = _apply(T, s, e.poses)
    errors = np.linalg.norm(aligned[:, :3, 3] - r.positions, axis=1)
    rot = np.array([rotation_angle(inverse(a) @ b) for a, b in zip(aligned, r.poses)])
    out = _stats(errors)
    out.update(errors=errors, rotation_rmse_deg=float(np.rad2deg(np.sqrt(np.mean(rot**2)))), scale=s,
               timestamps=r.timestamps)
    return out


def worst_pose_times(ate_figures: dict, share: float = 0.1) -> np.ndarray:
    """Reference timestamps [s] of the ``share`` of matched poses with the largest error in
    :func:`ate`'s figures (at least one), largest first."""
    errors = np.asarray(ate_figures["errors"])
    count = max(1, int(round(share * len(errors))))
    return np.asarray(ate_figures["timestamps"])[np.argsort(errors, kind="stable")[::-1][:count]]


def rpe(est: Trajectory, ref: Trajectory, delta: float = 1, unit: DeltaUnit | str = DeltaUnit.FRAMES,
        max_diff: float = 0.02) -> dict:
    """Relative pose error over pose pairs ``delta`` frames (or metres of reference path) apart.

    ``unit`` is a :class:`DeltaUnit` (or its string); in frames ``delta`` is a positive whole
    number. Returns translational stats [m] and ``rotation_*`` stats [deg].
    """
    unit = DeltaUnit(unit)
    if unit == DeltaUnit.FRAMES and not (float(delta).is_integer() and delta >= 1):
        raise ConfigError(f"RPE delta in frames must be a whole number >= 1, not {delta!r}")
    if unit == DeltaUnit.METERS and not delta > 0:
        raise ConfigError(f"RPE delta in meters must be > 0, not {delta!r}")
    i_e, i_r = associate(est, ref, max_diff)
    e, r = est.poses[i_e], ref.poses[i_r]
    if unit == DeltaUnit.FRAMES:
        step = int(delta)
        pairs = [(k, k + step) for k in range(len(e) - step)]
    else:
        dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(r[:, :3, 3], axis=0), axis=1))])
        ends = np.searchsorted(dist, dist + delta)
        pairs = [(k, int(j)) for k, j in enumerate(ends) if j < len(r)]
    if not pairs:
        raise SubmapSlamError(f"trajectory too short for RPE with delta {delta} {unit}")
    a, b = np.array(pairs).T
    E = inverse(inverse(r[a]) @ r[b]) @ (inverse(e[a]) @ e[b])
    trans = np.linalg.norm(E[:, :3, 3], axis=1)
    rot = np.rad2deg(np.array([rotation_angle(x) for x in E]))
    out = _stats(trans)
    out.update({f"rotation_{k}": v for k, v in _stats(rot).items() if k != "n"})
    return out


def relations_error(est: Trajectory, relations, max_diff: float = 0.02) -> dict:
    """Relations metric of Kümmerle et al. 2009: compare estimated relative poses with relations.

    For each relation ``(t_a, t_b, T_a_b)`` whose stamps both match estimate poses, the error is
    ``T_a_b^-1 (T_w_a^-1 T_w_b)``; returns mean and std of the translational error [m] and of
    the absolute rotational error [deg], their squared variants, and the count used.
    """
    ia = nearest_stamps(est.timestamps, relations.t_a, max_diff)
    ib = nearest_stamps(est.timestamps, relations.t_b, max_diff)
    ok = (ia >= 0) & (ib >= 0)
    if not ok.any():
        raise SubmapSlamError(f"no relation matches the estimate's timestamps within {max_diff} s")
    E = inverse(relations.T_a_b[ok]) @ (inverse(est.poses[ia[ok]]) @ est.poses[ib[ok]])
    trans = np.linalg.norm(E[:, :3, 3], axis=1)
    rot = np.rad2deg(np.array([rotation_angle(x) for x in E]))
    return {
        "n": int(ok.sum()), "trans_mean": float(trans.mean()), "trans_std": float(trans.std()),
        "rot_mean_deg": float(rot.mean()), "rot_std_deg": float(rot.std()),
        "trans_sq_mean": float((trans**2).mean()), "rot_sq_mean_deg2": float((rot**2).mean()),
    }


def kitti_segment_error(est: Trajectory, ref: Trajectory, lengths: tuple[float, ...] | None = None,
                        step: int = 10, max_diff: float = 0.02) -> dict:
    """KITTI-devkit style drift: for start frames every ``step`` and each segment length, the
    relative pose error at the end of the segment, as % of the length and deg/m.

    ``lengths`` default to 100..800 m, scaled down to 10%..80% of the path for short runs.
    """
    i_e, i_r = associate(est, ref, max_diff)
    e, r = est.poses[i_e], ref.poses[i_r]
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(r[:, :3, 3], axis=0), axis=1))])
    if lengths is None:
        lengths = tuple(range(100, 801, 100)) if dist[-1] > 1600 else tuple(dist[-1] * f for f in np.arange(0.1, 0.81, 0.1))
    t_err, r_err = [], []
    for first in range(0, len(r), step):
        for length in lengths:
            last = int(np.searchsorted(dist, dist[first] + length))
            if last >= len(r) or length <= 0:
                continue
            E = inverse(inverse(r[first]) @ r[last]) @ (inverse(e[first]) @ e[last])
            t_err.append(np.linalg.norm(E[:3, 3]) / length)
            r_err.append(rotation_angle(E) / length)
    if not t_err:
        raise SubmapSlamError("trajectory too short for segment errors")
    return {"trans_percent": float(100 * np.mean(t_err)), "rot_deg_per_m": float(np.rad2deg(np.mean(r_err))),
            "segments": len(t_err), "lengths_m": [float(x) for x in lengths]}
