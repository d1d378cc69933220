"""Trajectory evaluation: absolute and relative pose error (ATE/APE, RPE), as in ``evo``.

The conventions are those of evo (github.com/MichaelGrupp/evo, ``evo/core/metrics.py``,
``geometry.py``, ``filters.py``, ``trajectory.py``), so that numbers agree with ``evo_ape`` /
``evo_rpe`` on the same associated pose pairs:

* Association: nearest timestamps within ``max_dt`` seconds via
  :func:`data_tools.trajectory.associate` (one-to-one, greedy from the smallest difference,
  TUM's ``associate.py`` rule). evo's ``sync.associate_trajectories`` instead takes, for every
  pose of the shorter trajectory, the nearest pose of the longer one, so one pose of the longer
  trajectory may be used twice when it has a gap; on gap-free data both give the same pairs.
  Our default ``max_dt`` is TUM's 0.02 s; evo's default is 0.01 s.
* Alignment (estimate onto reference, on the associated positions): ``se3`` Umeyama/Horn rigid,
  ``sim3`` Umeyama with scale (positions scaled by s first, then the rigid motion applied, so the
  aligned poses stay rigid), ``origin`` (first associated estimate pose moved onto the first
  associated reference pose, evo's ``align_origin``), ``none``, and ``auto`` (the default of
  the CLI): se3 when the estimate's motion determines a rotation (at least
  :data:`ILL_CONDITIONED_MIN_POSES` associated poses spread in two directions, spread ratio >=
  :data:`ILL_CONDITIONED_SPREAD_RATIO`), else origin - a short or straight run is then compared
  from its first pose instead of through a rotation fitted to noise. The result records the mode
  used (``se3`` or ``origin``) and that ``auto`` chose it (:attr:`Alignment.label`).
* APE error pose ``E_i = P_i^-1 Q_i`` (estimate P, reference Q); translation error is
  ``|p_i - q_i|`` (metres).
* RPE error pose ``E_ij = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)``; the index pairs (i, j) are chosen on the
  estimate (evo's default) by index distance (``delta_unit="frames"``) or travelled path length
  (``delta_unit="m"``, evo's ``filter_pairs_by_path``).
* Statistics: rmse, mean, median, std (population, ``np.std``), min, max.

Units: positions and translation errors in metres, angles in degrees or radians as the relation
name says, timestamps in seconds.
"""
from __future__ import annotations

import json
import os
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from data_tools.errors import ConfigError, FormatError, RealgapError
from data_tools.geometry import invert_pose, rotation_angle_rad
from data_tools.trajectory import DEFAULT_MAX_DT, Trajectory, associate, read_tum, write_tum

ALIGN_HELP = ("alignment of the estimate onto the reference before absolute errors: auto (se3 when the run has "
              ">= 10 poses spread in two directions, else origin), se3, sim3, origin (first poses), none")
"""Help text of every ``--align`` option (``eval``, ``batch``, ``demo``)."""

STAT_KEYS = ("rmse", "mean", "median", "std", "min", "max")
"""Keys of :attr:`MetricResult.stats`, in evo's order (evo also reports sse)."""


# --------------------------------------------------------------------------------------------
# configuration


@dataclass
class EvalConfig:
    """Options of a trajectory evaluation (saved as JSON next to the outputs)."""

    align: str = field(default="auto", metadata={"help": ALIGN_HELP})
    """Alignment mode, a key of :data:`ALIGNERS` (auto, se3, sim3, origin, none)."""
    max_dt: float = field(default=DEFAULT_MAX_DT, metadata={"help": "largest timestamp difference of an associated pose pair, seconds"})
    """Largest |t_ref - t_est| of an associated pose pair, seconds (TUM: 0.02; evo: 0.01)."""
    delta: float = field(default=1.0, metadata={"help": "RPE pair distance, in --delta-unit"})
    """RPE distance between the two poses of a pair, in ``delta_unit``."""
    delta_unit: str = field(default="frames", metadata={"help": "unit of --delta: frames | m (travelled path length)"})
    """Unit of ``delta``: ``frames`` (index distance) or ``m`` (travelled path length, metres)."""
    all_pairs: bool = field(default=False, metadata={"help": "RPE over all pairs at distance delta, not only consecutive ones"})
    """RPE over all pairs at distance delta instead of consecutive non-overlapping ones."""
    rel_delta_tol: float = field(default=0.1, metadata={"help": "relative tolerance of a metres delta in all-pairs mode"})
    """Relative tolerance of a path-length delta in all-pairs mode (evo's default 0.1)."""
    strict_timestamps: bool = field(default=False, metadata={"help": "a pose whose timestamp repeats the previous one is an error (default: keep the first and warn, as evo does)"})
    """Without it trajectories are read like evo reads them: of an exactly repeated timestamp the
    first pose is kept and one warning names the file and line (:func:`data_tools.trajectory.read_tum`,
    the one reader; the official TUM fr2/desk ground truth has one). With it such a file is an error."""

    def validate(self) -> "EvalConfig":
        if self.align not in ALIGNERS:
            raise ConfigError(f"unknown alignment {self.align!r}; choose one of {', '.join(ALIGNERS)}")
        if not (np.isfinite(self.max_dt) and self.max_dt >= 0):
            raise ConfigError(f"max_dt must be a non-negative number of seconds, got {self.max_dt}")
        _check_delta(self.delta, self.delta_unit)
        if not (np.isfinite(self.rel_delta_tol) and self.rel_delta_tol >= 0):
            raise ConfigError(f"rel_delta_tol must be >= 0, got {self.rel_delta_tol}")
        return self

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "EvalConfig":
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ConfigError(f"unknown evaluation option(s): {', '.join(sorted(unknown))}")
        return cls(**d).validate()


PRESETS: dict[str, EvalConfig] = {
    "tum": EvalConfig(),
    "evo": EvalConfig(max_dt=0.01),
}
"""Named presets: ``tum`` (TUM benchmark: association within 0.02 s, auto alignment) and
``evo`` (``evo_ape -a`` / ``evo_rpe`` defaults: association within 0.01 s)."""


# --------------------------------------------------------------------------------------------
# alignment


def umeyama_alignment(X: np.ndarray, Y: np.ndarray, with_scale: bool = False
                      ) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity (R, t, s) with ``Y ~ s R X + t`` (Umeyama 1991, as evo).

    X, Y: (3, N) corresponding points (metres). Returns R (3, 3) rotation, t (3,) metres and
    s (scale; 1.0 unless ``with_scale``). Raises RealgapError for mismatched shapes or a
    degenerate configuration (all points on a line or a point: rotation undetermined).
    """
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    if X.shape != Y.shape or X.ndim != 2:
        raise RealgapError(f"umeyama_alignment: point sets must have the same (m, N) shape, got {X.shape} and {Y.shape}")
    m, n = X.shape
    mean_x = X.mean(axis=1)
    mean_y = Y.mean(axis=1)
    Xc = X - mean_x[:, None]
    Yc = Y - mean_y[:, None]
    sigma_x = float(np.sum(Xc * Xc)) / n                      # eq. 36
    cov_xy = (Yc @ Xc.T) / n                                   # eq. 38
    U, d, Vt = np.linalg.svd(cov_xy)
    if np.count_nonzero(d > np.finfo(d.dtype).eps) < m - 1:
        raise RealgapError("Umeyama alignment is degenerate: the estimated positions are (nearly) "
                           "collinear or identical, so the rotation is undetermined")
    S = np.eye(m)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:            # eq. 43, reflection guard
        S[m - 1, m - 1] = -1.0
    R = U @ S @ Vt                                             # eq. 40
    s = float(np.trace(np.diag(d) @ S) / sigma_x) if with_scale else 1.0   # eq. 42
    t = mean_y - s * (R @ mean_x)                              # eq. 41
    return R, t, s


@dataclass
class Alignment:
    """A similarity transform ``x -> s R x + t`` applied to an estimate (world frame, metres)."""

    mode: str
    """Alignment mode that produced it (key of :data:`ALIGNERS`)."""
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    """(3, 3) rotation."""
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """(3,) translation, metres."""
    s: float = 1.0
    """Scale factor (1 except for sim3)."""
    requested: str = ""
    """The mode asked for when it differs from ``mode`` (``auto``, which chose se3 or origin); else ''."""

    def __post_init__(self) -> None:
        self.R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        self.t = np.asarray(self.t, dtype=np.float64).reshape(3)
        self.s = float(self.s)

    @property
    def matrix(self) -> np.ndarray:
        """4x4 Sim(3) matrix [[s R, t], [0, 1]] (evo's ``alignment_transformation_sim3``)."""
        T = np.eye(4)
        T[:3, :3] = self.s * self.R
        T[:3, 3] = self.t
        return T

    def apply(self, traj: Trajectory) -> Trajectory:
        """The trajectory with positions ``s R p + t`` and rotations ``R R_p`` (poses stay rigid)."""
        poses = traj.poses.copy()
        poses[:, :3, :3] = np.einsum("ij,njk->nik", self.R, traj.poses[:, :3, :3])
        poses[:, :3, 3] = self.s * traj.positions @ self.R.T + self.t
        return Trajectory(traj.timestamps.copy(), poses)

    def to_dict(self) -> dict:
        return {"mode": self.mode, "requested": self.requested or self.mode, "label": self.label,
                "R": self.R.tolist(), "t": self.t.tolist(), "s": self.s, "matrix": self.matrix.tolist()}

    @property
    def label(self) -> str:
        """How the estimate was aligned, as printed next to every number: ``se3`` or ``auto: origin``."""
        return f"{self.requested}: {self.mode}" if self.requested and self.requested != self.mode else self.mode

    @classmethod
    def from_dict(cls, d: dict) -> "Alignment":
        req = d.get("requested", "")
        return cls(d["mode"], np.array(d["R"]), np.array(d["t"]), float(d["s"]), "" if req == d["mode"] else req)


class Aligner(ABC):
    """Estimates the :class:`Alignment` of an estimate onto a reference (associated poses)."""

    name: str = ""
    min_pairs: int = 1
    """Fewest associated pose pairs the method needs."""

    @abstractmethod
    def estimate(self, ref: Trajectory, est: Trajectory) -> Alignment:
        """ref, est: associated trajectories of equal length >= ``min_pairs``."""


ALIGNERS: dict[str, Aligner] = {}
"""Alignment methods by name (registry; add one with :func:`register_aligner`)."""


def register_aligner(cls: type[Aligner]) -> type[Aligner]:
    ALIGNERS[cls.name] = cls()
    return cls


@register_aligner
class NoAlignment(Aligner):
    """Identity: the estimate is compared as it is."""

    name = "none"

    def estimate(self, ref, est):
        return Alignment(self.name)


@register_aligner
class SE3Alignment(Aligner):
    """Rigid least-squares fit of the estimated positions onto the reference (Horn/Umeyama)."""

    name = "se3"
    min_pairs = 3

    def estimate(self, ref, est):
        R, t, s = umeyama_alignment(est.positions.T, ref.positions.T, with_scale=False)
        return Alignment(self.name, R, t, s)


@register_aligner
class Sim3Alignment(Aligner):
    """Similarity least-squares fit (rotation, translation, scale): for monocular estimates."""

    name = "sim3"
    min_pairs = 3

    def estimate(self, ref, est):
        R, t, s = umeyama_alignment(est.positions.T, ref.positions.T, with_scale=True)
        return Alignment(self.name, R, t, s)


@register_aligner
class OriginAlignment(Aligner):
    """The first estimate pose moved onto the first reference pose (evo's ``align_origin``)."""

    name = "origin"

    def estimate(self, ref, est):
        P0, Q0 = est.poses[0], ref.poses[0]
        T = Q0 @ invert_pose(P0)
        return Alignment(self.name, T[:3, :3], T[:3, 3], 1.0)


@register_aligner
class AutoAlignment(Aligner):
    """se3 when the estimate determines a rotation (:func:`is_well_conditioned`), else origin: the
    default of the CLI, so that a short or straight run is not scored through a rotation fitted
    to noise (issue 44: a 30-frame chess run scored 23 deg APE rotation after SE(3), 0.2 deg from its first pose)."""

    name = "auto"

    def estimate(self, ref, est):
        mode = "se3" if is_well_conditioned(est) else "origin"
        a = ALIGNERS[mode].estimate(ref, est)
        return Alignment(mode, a.R, a.t, a.s, requested=self.name)


def align(ref: Trajectory, est: Trajectory, mode: str = "se3") -> tuple[Trajectory, Alignment]:
    """Align ``est`` onto ``ref`` (already associated: same length, pose k matches pose k).

    Returns the aligned estimate and the :class:`Alignment` (``.matrix`` is the 4x4 Sim(3),
    ``.s`` the scale).
    """
    aligner = ALIGNERS.get(mode)
    if aligner is None:
        raise ConfigError(f"unknown alignment {mode!r}; choose one of {', '.join(ALIGNERS)}")
    if len(ref) != len(est):
        raise RealgapError(f"align: trajectories must be associated first ({len(ref)} vs {len(est)} poses)")
    if len(est) < aligner.min_pairs:
        raise RealgapError(f"{mode} alignment needs at least {aligner.min_pairs} associated poses, got {len(est)}")
    if aligner.min_pairs >= 3:
        warn_if_ill_conditioned(est, mode)
    a = aligner.estimate(ref, est)
    return a.apply(est), a


ILL_CONDITIONED_MIN_POSES = 10
"""Fewer associated poses than this make a rotational alignment (se3, sim3) ill-conditioned."""
ILL_CONDITIONED_SPREAD_RATIO = 0.05
"""... as does a position cloud whose second principal extent is below this fraction of the first
(near-collinear motion: the rotation about the line of travel is set by noise)."""


def alignment_condition(est: Trajectory) -> float:
    """sigma_2 / sigma_1 of the centred positions (1 = isotropic spread, 0 = collinear or a point)."""
    P = est.positions - est.positions.mean(axis=0)
    sv = np.linalg.svd(P, compute_uv=False) if len(P) else np.zeros(3)
    return float(sv[1] / sv[0]) if len(sv) > 1 and sv[0] > 0 else 0.0


def is_well_conditioned(est: Trajectory) -> bool:
    """Whether a rotational alignment (se3, sim3) of ``est`` is determined: at least
    :data:`ILL_CONDITIONED_MIN_POSES` poses whose positions spread in two directions."""
    return len(est) >= ILL_CONDITIONED_MIN_POSES and alignment_condition(est) >= ILL_CONDITIONED_SPREAD_RATIO


def warn_if_ill_conditioned(est: Trajectory, mode: str) -> None:
    """One realgap warning (:func:`data_tools.errors.warn`) when an explicitly requested rotational
    alignment rests on too few poses or on near-collinear motion: the fitted rotation, and every
    rotation error after it, is then unreliable (``--align auto``, ``origin`` or ``none`` avoid it)."""
    from data_tools.errors import warn
    n, ratio = len(est), alignment_condition(est)
    if not is_well_conditioned(est):
        why = (f"only {n} associated poses" if n < ILL_CONDITIONED_MIN_POSES else
               f"near-collinear motion (spread ratio {ratio:.3f} < {ILL_CONDITIONED_SPREAD_RATIO})")
        warn(f"{mode} alignment is ill-conditioned: {why}; the fitted rotation and rotation errors "
             f"are unreliable (--align auto or origin compares from the first pose)")


# --------------------------------------------------------------------------------------------
# association


def associate_trajectories(ref: Trajectory, est: Trajectory, max_dt: float = DEFAULT_MAX_DT,
                           ref_name: str = "reference", est_name: str = "estimate"
                           ) -> tuple[Trajectory, Trajectory]:
    """The associated sub-trajectories (ref_k, est_k), nearest timestamps within ``max_dt`` s.

    One-to-one matching by :func:`data_tools.trajectory.associate`. Raises RealgapError naming
    both trajectories and their time ranges when no pair is found.
    """
    ia, ib = associate(ref.timestamps, est.timestamps, max_dt)
    if len(ia) == 0:
        raise RealgapError(
            f"no associated poses between {ref_name} ({_time_range(ref)}) and {est_name} "
            f"({_time_range(est)}) within max_dt {max_dt:g} s")
    return ref.subset(ia), est.subset(ib)


def _time_range(traj: Trajectory) -> str:
    if len(traj) == 0:
        return "0 poses"
    return f"{len(traj)} poses, t = {traj.timestamps[0]:.3f}..{traj.timestamps[-1]:.3f} s"


# --------------------------------------------------------------------------------------------
# pose relations (what an error pose E is measured by)


class Relation(ABC):
    """Turns error poses E (N, 4, 4) into scalar errors (N,)."""

    name: str = ""
    unit: str = ""
    """Unit of the errors: m, deg, rad or '' (dimensionless)."""
    evo_name: str = ""
    """Name of the member of evo's ``PoseRelation``."""

    @abstractmethod
    def errors(self, E: np.ndarray) -> np.ndarray:
        ...


RELATIONS: dict[str, Relation] = {}
"""Pose relations by name (registry; add one with :func:`register_relation`)."""


def register_relation(cls: type[Relation]) -> type[Relation]:
    RELATIONS[cls.name] = cls()
    return cls


@register_relation
class TranslationPart(Relation):
    """Length of the translation of E, metres (evo ``translation_part``)."""

    name, unit, evo_name = "translation", "m", "translation_part"

    def errors(self, E):
        return np.linalg.norm(E[:, :3, 3], axis=1)


@register_relation
class RotationAngleDeg(Relation):
    """Rotation angle of E, degrees (evo ``rotation_angle_deg``)."""

    name, unit, evo_name = "rotation_angle_deg", "deg", "rotation_angle_deg"

    def errors(self, E):
        return np.rad2deg(rotation_angle_rad(E[:, :3, :3]))


@register_relation
class RotationAngleRad(Relation):
    """Rotation angle of E, radians (evo ``rotation_angle_rad``)."""

    name, unit, evo_name = "rotation_angle_rad", "rad", "rotation_angle_rad"

    def errors(self, E):
        return rotation_angle_rad(E[:, :3, :3])


@register_relation
class FullTransformation(Relation):
    """Frobenius norm of E - I, dimensionless: mixes metres and radians (evo ``full_transformation``)."""

    name, unit, evo_name = "full", "", "full_transformation"

    def errors(self, E):
        return np.linalg.norm((E - np.eye(4)).reshape(len(E), -1), axis=1)


def _relation(name: str) -> Relation:
    rel = RELATIONS.get(name)
    if rel is None:
        raise ConfigError(f"unknown pose relation {name!r}; choose one of {', '.join(RELATIONS)}")
    return rel


# --------------------------------------------------------------------------------------------
# RPE pair selection


def pairs_by_index(n: int, delta: int, all_pairs: bool = False) -> np.ndarray:
    """(K, 2) index pairs (i, i + delta); consecutive ones are 0-delta, delta-2 delta, ... (evo)."""
    if all_pairs:
        i = np.arange(max(n - delta, 0))
        return np.stack([i, i + delta], axis=1).astype(int)
    ids = np.arange(0, n, delta)
    return np.stack([ids[:-1], ids[1:]], axis=1).astype(int)


def pairs_by_path(positions: np.ndarray, delta_m: float, tol_m: float = 0.0,
                  all_pairs: bool = False) -> np.ndarray:
    """(K, 2) index pairs about ``delta_m`` metres of travelled path apart (evo ``filter_pairs_by_path``).

    Consecutive mode: walk along the path from pose 0; each time the path since the last chosen
    pose reaches ``delta_m``, that pose is chosen; pairs join successive chosen poses. All-pairs
    mode: for each i the j > i whose path distance is closest to ``delta_m``, kept when within
    ``tol_m``.
    """
    p = np.asarray(positions, dtype=np.float64)
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    if all_pairs:
        dist = np.concatenate([[0.0], np.cumsum(steps)])
        out = []
        for i in range(len(dist) - 1):
            d = dist[i + 1:] - dist[i]
            k = int(np.argmin(np.abs(d - delta_m)))
            if abs(d[k] - delta_m) <= tol_m:
                out.append((i, i + 1 + k))
        return np.array(out, dtype=int).reshape(-1, 2)
    ids = [0]
    acc = 0.0
    for i, st in enumerate(steps, start=1):   # sequential sum, like evo (not a cumsum difference)
        acc += float(st)
        if acc >= delta_m:
            ids.append(i)
            acc = 0.0
    ids = np.array(ids, dtype=int)
    return np.stack([ids[:-1], ids[1:]], axis=1)


DELTA_UNITS = {
    "frames": lambda traj, delta, tol, all_pairs: pairs_by_index(len(traj), int(delta), all_pairs),
    "m": lambda traj, delta, tol, all_pairs: pairs_by_path(traj.positions, delta, tol, all_pairs),
}
"""RPE pair selectors by delta unit: fn(trajectory, delta, absolute tolerance, all_pairs) -> (K, 2)."""


def _check_delta(delta: float, delta_unit: str) -> None:
    if delta_unit not in DELTA_UNITS:
        raise ConfigError(f"unknown delta unit {delta_unit!r}; choose one of {', '.join(DELTA_UNITS)}")
    if not (np.isfinite(delta) and delta > 0):
        raise ConfigError(f"RPE delta must be > 0, got {delta}")
    if delta_unit == "frames" and float(delta) != int(delta):
        raise ConfigError(f"RPE delta in frames must be an integer, got {delta}")


# --------------------------------------------------------------------------------------------
# results


def statistics(errors: np.ndarray) -> dict[str, float]:
    """rmse, mean, median, std (population), min, max of an error array (evo's definitions)."""
    e = np.asarray(errors, dtype=np.float64)
    if e.size == 0:
        raise RealgapError("no errors to summarise")
    return {"rmse": float(np.sqrt(np.mean(e * e))), "mean": float(np.mean(e)),
            "median": float(np.median(e)), "std": float(np.std(e)),
            "min": float(np.min(e)), "max": float(np.max(e))}


@dataclass
class MetricResult:
    """One trajectory metric: per-pair errors, their statistics and what produced them."""

    metric: str
    """``ape`` or ``rpe``."""
    relation: str
    """Pose relation (key of :data:`RELATIONS`)."""
    unit: str
    """Unit of errors and stats: m, deg, rad or '' (dimensionless)."""
    stats: dict[str, float]
    """rmse, mean, median, std, min, max in ``unit``."""
    pairs: int
    """Number of associated (reference, estimate) pose pairs used."""
    errors: np.ndarray
    """(M,) error per pose (APE, M = pairs) or per relative pose pair (RPE), in ``unit``."""
    timestamps: np.ndarray
    """(M,) estimate timestamp of each error, seconds (RPE: the later pose j of the pair)."""
    aligned: Trajectory
    """Associated estimate after alignment (``pairs`` poses)."""
    reference: Trajectory
    """Associated reference (``pairs`` poses)."""
    alignment: Alignment
    """Transform applied to the estimate (mode, R, t, s)."""
    index_pairs: np.ndarray | None = None
    """RPE only: (M, 2) indices (i, j) into ``aligned``/``reference`` of each relative pair."""
    info: dict = field(default_factory=dict)
    """Free-form metadata: names, max_dt, delta, delta_unit, title (JSON-serialisable)."""

    @property
    def rmse(self) -> float:
        return self.stats["rmse"]

    def to_dict(self) -> dict:
        """JSON-ready summary: stats at top level, plus pairs, align, info."""
        d = {"metric": self.metric, "relation": self.relation, "unit": self.unit}
        d.update({k: float(self.stats[k]) for k in STAT_KEYS})
        d["pairs"] = int(self.pairs)
        d["n_errors"] = int(len(self.errors))
        d["align"] = self.alignment.mode          # the mode used; alignment.label says whether auto chose it
        d["alignment"] = self.alignment.to_dict()
        d["info"] = self.info
        return d

    def to_json(self, indent: int | None = 2) -> str:
        return json.dumps(self.to_dict(), indent=indent)

    def title(self) -> str:
        u = f" {self.unit}" if self.unit else ""
        return f"{self.metric.upper()} ({self.relation}, align {self.alignment.label}): rmse {self.rmse:.4g}{u}"

    # evo save_res_file style, as a folder
    def save(self, directory: str | os.PathLike) -> Path:
        """Write info.json, stats.json, errors.npy, timestamps.npy, (index_pairs.npy),
        estimate_aligned.txt and reference.txt (TUM) into ``directory``; returns it."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        info = {"metric": self.metric, "relation": self.relation, "unit": self.unit,
                "pairs": int(self.pairs), "alignment": self.alignment.to_dict(), "info": self.info}
        from data_tools.results import atomic_save_npy, atomic_write_json
        atomic_write_json(d / "info.json", info)
        atomic_write_json(d / "stats.json", {k: float(self.stats[k]) for k in STAT_KEYS})
        atomic_save_npy(d / "errors.npy", np.asarray(self.errors, dtype=np.float64))
        atomic_save_npy(d / "timestamps.npy", np.asarray(self.timestamps, dtype=np.float64))
        if self.index_pairs is not None:
            atomic_save_npy(d / "index_pairs.npy", np.asarray(self.index_pairs, dtype=np.int64))
        hdr = f"{self.metric} {self.relation}: estimate aligned by {self.alignment.label}"
        write_tum(d / "estimate_aligned.txt", self.aligned, header=hdr)
        write_tum(d / "reference.txt", self.reference, header="associated reference")
        return d

    @classmethod
    def load(cls, directory: str | os.PathLike) -> "MetricResult":
        """Read a folder written by :meth:`save` (poses come back with the 9 significant
        digits of the TUM files; errors, stats and timestamps exactly)."""
        d = Path(directory)
        for name in ("info.json", "stats.json", "errors.npy", "timestamps.npy", "estimate_aligned.txt", "reference.txt"):
            if not (d / name).is_file():
                raise FormatError(d, f"not a metric result folder ({name} missing)")
        try:
            info = json.loads((d / "info.json").read_text())
            stats = json.loads((d / "stats.json").read_text())
        except json.JSONDecodeError as e:
            raise FormatError(d, f"invalid JSON in result folder: {e}") from None
        pairs_path = d / "index_pairs.npy"
        return cls(metric=info["metric"], relation=info["relation"], unit=info["unit"],
                   stats={k: float(stats[k]) for k in STAT_KEYS}, pairs=int(info["pairs"]),
                   errors=np.load(d / "errors.npy"), timestamps=np.load(d / "timestamps.npy"),
                   aligned=read_tum(d / "estimate_aligned.txt"), reference=read_tum(d / "reference.txt"),
                   alignment=Alignment.from_dict(info["alignment"]),
                   index_pairs=np.load(pairs_path) if pairs_path.is_file() else None,
                   info=info.get("info", {}))


# --------------------------------------------------------------------------------------------
# metrics


def _prepare(ref, est, align_mode, max_dt, ref_name, est_name):
    if align_mode not in ALIGNERS:
        raise ConfigError(f"unknown alignment {align_mode!r}; choose one of {', '.join(ALIGNERS)}")
    r, e = associate_trajectories(ref, est, max_dt, ref_name, est_name)
    need = ALIGNERS[align_mode].min_pairs
    if len(r) < need:
        raise RealgapError(f"{align_mode} alignment needs at least {need} associated poses, but {ref_name} "
                           f"and {est_name} share only {len(r)} within max_dt {max_dt:g} s")
    e_al, a = align(r, e, align_mode)
    return r, e_al, a


def ape(ref: Trajectory, est: Trajectory, relation: str = "translation", align: str = "se3",
        max_dt: float = DEFAULT_MAX_DT, ref_name: str = "reference", est_name: str = "estimate"
        ) -> MetricResult:
    """Absolute pose error of ``est`` against ``ref`` after association and alignment (evo_ape).

    relation: translation (m) | rotation_angle_deg | rotation_angle_rad | full (see RELATIONS).
    align: se3 | sim3 | origin | none (se3/sim3 need >= 3 associated poses).
    """
    rel = _relation(relation)
    r, e, a = _prepare(ref, est, align, max_dt, ref_name, est_name)
    if rel.name == "translation":
        errors = np.linalg.norm(e.positions - r.positions, axis=1)   # as evo: no full poses needed
    else:
        errors = rel.errors(invert_pose(e.poses) @ r.poses)             # E_i = P_i^-1 Q_i
    info = {"ref_name": ref_name, "est_name": est_name, "max_dt": float(max_dt)}
    return MetricResult("ape", rel.name, rel.unit, statistics(errors), len(r), errors,
                        e.timestamps.copy(), e, r, a, None, info)


def ate(ref: Trajectory, est: Trajectory, align: str = "se3", max_dt: float = DEFAULT_MAX_DT,
        ref_name: str = "reference", est_name: str = "estimate") -> MetricResult:
    """Absolute trajectory error: translation APE in metres after ``align`` (default SE(3))."""
    return ape(ref, est, "translation", align, max_dt, ref_name, est_name)


def rpe(ref: Trajectory, est: Trajectory, delta: float = 1, delta_unit: str = "frames",
        relation: str = "translation", all_pairs: bool = False, align: str = "none",
        max_dt: float = DEFAULT_MAX_DT, rel_delta_tol: float = 0.1,
        pairs_from_reference: bool = False, ref_name: str = "reference", est_name: str = "estimate"
        ) -> MetricResult:
    """Relative pose error over pose pairs ``delta`` apart (evo_rpe).

    delta_unit ``frames``: index distance in the associated trajectories; ``m``: travelled path
    length in metres (measured on the aligned estimate unless ``pairs_from_reference``;
    ``rel_delta_tol * delta`` is the tolerance in all-pairs mode). ``align`` defaults to
    ``none`` as in evo_rpe; RPE is invariant to an SE(3) alignment, not to a Sim(3) one.
    """
    rel = _relation(relation)
    _check_delta(delta, delta_unit)
    r, e, a = _prepare(ref, est, align, max_dt, ref_name, est_name)
    if len(r) < 2:
        raise RealgapError(f"RPE needs at least 2 associated poses, {ref_name} and {est_name} share {len(r)}")
    base = r if pairs_from_reference else e
    ij = DELTA_UNITS[delta_unit](base, delta, delta * rel_delta_tol, all_pairs)
    if len(ij) == 0:
        raise RealgapError(f"RPE delta = {delta:g} {delta_unit} produced no pose pairs among {len(r)} "
                           f"associated poses: use a smaller delta")
    i, j = ij[:, 0], ij[:, 1]
    Q_rel = invert_pose(r.poses[i]) @ r.poses[j]
    P_rel = invert_pose(e.poses[i]) @ e.poses[j]
    errors = rel.errors(invert_pose(Q_rel) @ P_rel)
    info = {"ref_name": ref_name, "est_name": est_name, "max_dt": float(max_dt), "delta": float(delta),
            "delta_unit": delta_unit, "all_pairs": bool(all_pairs), "rel_delta_tol": float(rel_delta_tol),
            "pairs_from_reference": bool(pairs_from_reference)}
    return MetricResult("rpe", rel.name, rel.unit, statistics(errors), len(r), errors,
                        e.timestamps[j].copy(), e, r, a, ij, info)
