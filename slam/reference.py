"""Reference geometry for a measured sequence: one TSDF mesh fused from its frames at their
ground-truth poses, written as ``scene.json`` + ``meshes/`` so the sensor lab can compare the
sequence with a simulation of it.

Real sequences (TUM RGB-D, 7-Scenes) come without a CAD model of the scene. The best geometry
available is the surface that all their depth images agree on: fusing every frame at its
ground-truth pose into a TSDF averages the per-frame noise away (the zero crossing of the
weighted mean signed distance; with n observations the random part of the axial noise shrinks
~ 1/sqrt(n)) while systematic effects shared by all frames (a depth-scale error, lens
distortion seen from similar viewpoints) stay in it. This is an approximation and the
docstrings of the lab say so: a gap measured against a fused reference is a lower bound of
the gap against the true geometry for noise-like effects, and the reference inherits the
pose errors of the ground truth (motion capture for TUM, KinectFusion for 7-Scenes).

Cleaning: Open3D's marching cubes can emit a few triangles on edges shared by more than two
triangles (ambiguous cube configurations at block borders) and duplicate/degenerate faces;
scene meshes must be edge-manifold (:func:`data_tools.mesh.check_mesh`), so those triangles are
dropped, as are connected components smaller than ``min_component_triangles`` (floating
specks fused from a few flying pixels).

Layout written into ``OUT`` (a copy of the sequence unless ``OUT`` is the sequence itself)::

    OUT/scene.json, OUT/meshes/<name>.ply    the reference (world frame of groundtruth.txt, m)
    OUT/reference_config.json                ReferenceConfig + what was fused (frames, time)
    OUT/depth.txt, depth/, rgb.txt, rgb/, groundtruth.txt, camera.json   (copied / linked)
"""
from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from data_tools.camera import Camera, Intrinsics, SensorSpec, write_camera_json
from data_tools.errors import ConfigError, FormatError, RealgapError
from data_tools.mesh import TriMesh, check_mesh
from data_tools.outputs import check_input_dir, check_output_dir, clear_incomplete, mark_incomplete
from data_tools.scene_spec import Material, SceneSpec, write_scene_json
from data_tools.sequence import SequenceReader, link_or_copy, read_index, spread_indices
from slam.registration import config_from_dict, config_to_dict
from slam.tsdf import TSDFConfig, TSDFVolume

__all__ = ["ReferenceConfig", "ReferenceResult", "NAMED_CAMERAS", "named_camera", "fuse_reference",
           "clean_mesh", "make_reference", "REFERENCE_CONFIG_FILE"]

REFERENCE_CONFIG_FILE = "reference_config.json"

_KINECT_V1 = SensorSpec("structured_light", 0.075, (0.075, 0.0, 0.0), {"model": "kinect_v1"})

NAMED_CAMERAS: dict[str, Camera] = {
    "tum_fr1": Camera(Intrinsics(640, 480, 517.3, 516.5, 318.6, 255.3), 5000.0, _KINECT_V1),
    "tum_fr2": Camera(Intrinsics(640, 480, 520.9, 521.0, 325.1, 249.7), 5000.0, _KINECT_V1),
    "tum_fr3": Camera(Intrinsics(640, 480, 535.4, 539.2, 320.1, 247.6), 5000.0, _KINECT_V1),
    "sevenscenes": Camera(Intrinsics(640, 480, 585.0, 585.0, 320.0, 240.0), 1000.0, _KINECT_V1),
}
"""Cameras of public RGB-D datasets whose folders carry no camera.json: the TUM RGB-D depth
cameras fr1/fr2/fr3 (intrinsics from the dataset web page, depth_scale 5000) and the 7-Scenes
Kinect (585 px, depth in mm). All are Kinect v1 structured-light sensors (projector 7.5 cm at
camera +x)."""


def named_camera(name_or_path: str | os.PathLike) -> Camera:
    """A camera from :data:`NAMED_CAMERAS` or from a camera.json file."""
    from data_tools.camera import read_camera_json
    key = str(name_or_path)
    if key in NAMED_CAMERAS:
        return NAMED_CAMERAS[key]
    p = Path(key)
    if not p.is_file():
        raise ConfigError(f"camera {key!r} is neither a camera.json file nor a known camera "
                          f"({', '.join(NAMED_CAMERAS)})")
    return read_camera_json(p)


@dataclass
class ReferenceConfig:
    """How the reference mesh is fused and labelled (saved as OUT/reference_config.json)."""

    tsdf: TSDFConfig = field(default_factory=lambda: TSDFConfig(voxel_size_m=0.01, integrate_color=False,
                                                                depth_max_m=4.0))
    """TSDF options (1 cm voxels, 4 cm truncation, depth up to 4 m; colour is not needed)."""
    max_frames: int | None = None
    """Fuse only the first this many frames with a pose (``--max-frames``); None = every one."""
    spread_frames: int | None = None
    """Of those, fuse this many, evenly spread (``--spread-frames``); None = all of them."""
    mesh_weight_threshold: float = 0.0
    """Minimum number of fused observations of a voxel kept in the mesh; 0 = automatic:
    min(3, frames fused) (short sequences keep single-view surfaces)."""
    min_component_triangles: int = 200
    """Connected components with fewer triangles are dropped (floating specks)."""
    mesh_name: str = "reference"
    """Name of the mesh in scene.json (file meshes/<name>.ply)."""
    material: str = "reference"
    """Material name of the mesh (the lab bins errors by material)."""
    albedo: float = 0.5
    """Diffuse reflectance of that material in [0, 1] (unknown for real scenes: a mid value)."""
    specular: float = 0.0
    """Mirror-lobe weight of that material in [0, 1]."""

    def validate(self) -> "ReferenceConfig":
        self.tsdf.validate()
        for k in ("max_frames", "spread_frames"):
            if getattr(self, k) is not None and int(getattr(self, k)) < 1:
                raise ConfigError(f"{k} must be >= 1 (None: every frame), got {getattr(self, k)}")
        if self.mesh_weight_threshold < 0:
            raise ConfigError(f"mesh_weight_threshold must be >= 0, got {self.mesh_weight_threshold}")
        if int(self.min_component_triangles) < 0:
            raise ConfigError("min_component_triangles must be >= 0")
        for k in ("albedo", "specular"):
            v = float(getattr(self, k))
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"{k} must be in [0, 1], got {v}")
        if not self.mesh_name or "/" in self.mesh_name or not self.material:
            raise ConfigError("mesh_name and material must be non-empty names (no '/')")
        return self

    def to_dict(self) -> dict:
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, d: dict, where: str = "reference config") -> "ReferenceConfig":
        return config_from_dict(cls, d, where).validate()


@dataclass
class ReferenceResult:
    """What :func:`fuse_reference` / :func:`make_reference` produced."""

    mesh: TriMesh
    """The cleaned reference mesh (world frame, metres)."""
    frames_fused: int
    """Frames integrated into the TSDF."""
    frames_without_pose: int
    """Frames skipped because no ground-truth pose lies within 0.02 s."""
    triangles_dropped: int
    """Triangles removed by :func:`clean_mesh` (non-manifold, degenerate, small components)."""
    seconds: float
    """Wall time of reading + fusing + meshing."""
    out_dir: Path | None = None
    """Where scene.json was written (make_reference only)."""
    timestamps: list = field(default_factory=list)
    """Depth timestamps (s) of the frames fused, in order (which frames ``max_frames``/``spread_frames`` kept)."""

    def to_json(self) -> dict:
        lo, hi = self.mesh.bounds if len(self.mesh.vertices) else (np.zeros(3), np.zeros(3))
        return {"frames_fused": self.frames_fused, "frames_without_pose": self.frames_without_pose,
                "vertices": int(len(self.mesh.vertices)), "triangles": int(len(self.mesh.triangles)),
                "triangles_dropped": self.triangles_dropped, "bounds_m": [list(map(float, lo)), list(map(float, hi))],
                "seconds": round(self.seconds, 3), "timestamps_s": [float(t) for t in self.timestamps]}


def clean_mesh(mesh: TriMesh, min_component_triangles: int = 0) -> tuple[TriMesh, int]:
    """Drop degenerate and duplicate triangles, every triangle on an edge shared by more than two
    triangles, and connected components (via shared edges) smaller than
    ``min_component_triangles``; unused vertices are removed. Returns (mesh, triangles dropped)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    tri = np.asarray(mesh.triangles, dtype=np.int64)
    n0 = len(tri)
    if n0 == 0:
        return mesh, 0
    keep = (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])
    tri = tri[keep]
    _, first = np.unique(np.sort(tri, axis=1), axis=0, return_index=True)
    tri = tri[np.sort(first)]
    # one pass: every triangle on an edge shared by > 2 triangles goes, so that edge is gone and
    # the counts of all other edges can only fall
    e = np.sort(np.stack([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]], 1), axis=2)  # (F, 3, 2)
    _, inv, cnt = np.unique(e.reshape(-1, 2), axis=0, return_inverse=True, return_counts=True)
    tri = tri[~(cnt[inv.reshape(-1)] > 2).reshape(-1, 3).any(1)]
    if min_component_triangles > 0 and len(tri):
        e = np.sort(np.stack([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]], 1), axis=2).reshape(-1, 2)
        _, inv = np.unique(e, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        owner = np.repeat(np.arange(len(tri)), 3)
        # triangles sharing an edge: link each triangle to the first owner of each of its edges
        first_owner = np.full(inv.max() + 1, -1, np.int64)
        order = np.argsort(inv, kind="stable")
        first_owner[inv[order][::-1]] = owner[order][::-1]
        a = owner
        b = first_owner[inv]
        g = coo_matrix((np.ones(len(a)), (a, b)), shape=(len(tri), len(tri)))
        _, labels = connected_components(g, directed=False)
        sizes = np.bincount(labels)
        tri = tri[sizes[labels] >= min_component_triangles]
    used = np.unique(tri.reshape(-1))
    remap = np.full(len(mesh.vertices), -1, np.int64)
    remap[used] = np.arange(len(used))
    colors = None if mesh.vertex_colors is None else np.asarray(mesh.vertex_colors)[used]
    out = TriMesh(np.asarray(mesh.vertices)[used], remap[tri].astype(np.int32), name=mesh.name,
                  material=mesh.material, vertex_colors=colors)
    return out, n0 - len(tri)


def fuse_reference(sequence: SequenceReader | str | os.PathLike, config: ReferenceConfig | None = None, *,
                   camera: Camera | None = None, progress: bool = False) -> ReferenceResult:
    """Fuse the frames of ``sequence`` at their ground-truth poses into one TSDF and return its
    cleaned mesh (named ``config.mesh_name``, material ``config.material``).

    FormatError when the sequence has no ground truth or nothing could be fused.
    """
    cfg = (config or ReferenceConfig()).validate()
    reader = sequence if isinstance(sequence, SequenceReader) else SequenceReader(sequence, camera=camera)
    if not reader.has_groundtruth:
        raise FormatError(reader.path / "groundtruth.txt", "no ground-truth poses: cannot fuse a reference")
    has_pose = np.all(np.isfinite(reader.poses.reshape(len(reader), -1)), axis=1)
    idx = np.flatnonzero(has_pose).tolist()
    if not idx:
        raise FormatError(reader.path / "groundtruth.txt", "no ground-truth pose within 0.02 s of any depth frame")
    idx = idx[:None if cfg.max_frames is None else int(cfg.max_frames)]
    idx = [idx[i] for i in spread_indices(len(idx), None if cfg.spread_frames is None else int(cfg.spread_frames))]
    t0 = time.perf_counter()
    vol = TSDFVolume(cfg.tsdf)
    intr = reader.intrinsics
    bar = None
    if progress:
        from data_tools.progress import progress_bar
        bar = progress_bar(total=len(idx), desc="fusing reference", unit="frame", leave=False)
    for i in idx:
        depth = reader.read_depth(i)
        vol.integrate(depth, None, intr, reader.poses[i])
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    w = cfg.mesh_weight_threshold if cfg.mesh_weight_threshold > 0 else float(min(3, len(idx)))
    raw = vol.extract_mesh(w)
    raw = TriMesh(raw.vertices, raw.triangles, name=cfg.mesh_name, material=cfg.material)
    mesh, dropped = clean_mesh(raw, int(cfg.min_component_triangles))
    if len(mesh.triangles) == 0:
        raise FormatError(reader.path, f"the fused reference is empty ({len(idx)} frames fused; check the "
                                       f"depth scale, the poses and tsdf.depth_max_m)")
    check_mesh(mesh)
    return ReferenceResult(mesh, len(idx), int((~has_pose).sum()), dropped, time.perf_counter() - t0,
                           timestamps=[float(reader.timestamps[i]) for i in idx])




def _copy_sequence(reader: SequenceReader, out: Path, camera: Camera) -> None:
    """Copy (hard-link when possible) the index files and images of ``reader`` into ``out``."""
    src = reader.path
    out.mkdir(parents=True, exist_ok=True)
    for name in ("depth.txt", "rgb.txt", "groundtruth.txt"):
        if (src / name).is_file():
            shutil.copyfile(src / name, out / name)
    # every image the copied index files list (reader.depth_files holds only the depth frames
    # associated with a colour image, and the copied depth.txt lists all of them)
    for name in ("depth.txt", "rgb.txt"):
        if (src / name).is_file():
            for rel in read_index(src / name)[1]:
                link_or_copy(src / rel, out / rel)
    write_camera_json(out / "camera.json", camera)


def make_reference(seq_dir: str | os.PathLike, out_dir: str | os.PathLike | None = None,
                   config: ReferenceConfig | None = None, *, camera: Camera | None = None,
                   overwrite: bool = False, progress: bool = False) -> ReferenceResult:
    """Fuse the reference of ``seq_dir`` and write ``scene.json`` + ``meshes/`` (+
    reference_config.json) into ``out_dir`` (a copy of the sequence, images hard-linked when
    possible) or, with ``out_dir`` None, into ``seq_dir`` itself.

    camera: overrides the sequence's camera.json (and is written to the output), e.g.
    ``NAMED_CAMERAS["tum_fr1"]`` for TUM folders. An existing scene.json is an error unless
    ``overwrite``; a finished output (reference_config.json present) is not recomputed.
    """
    cfg = (config or ReferenceConfig()).validate()
    src = check_input_dir(seq_dir, "sequence folder")
    out = src if out_dir is None else check_output_dir(out_dir, what="output sequence folder")
    reader = SequenceReader(src, camera=camera)
    cam = camera or reader.camera
    meta_path = out / REFERENCE_CONFIG_FILE
    if (out / "scene.json").exists() and not overwrite:
        if meta_path.exists() and out != src:
            try:
                meta = json.loads(meta_path.read_text())
            except json.JSONDecodeError:
                meta = {}
            if meta.get("config") == cfg.to_dict() and meta.get("source") == str(src.resolve()):
                from data_tools.scene_spec import read_scene_json
                sc = read_scene_json(out / "scene.json")
                r = meta.get("result", {})
                return ReferenceResult(sc.meshes[0], int(r.get("frames_fused", 0)),
                                       int(r.get("frames_without_pose", 0)), int(r.get("triangles_dropped", 0)),
                                       0.0, out)
        raise RealgapError(f"{out / 'scene.json'}: already exists (use --overwrite to replace it)")
    if out != src:
        if out.exists() and any(out.iterdir()) and not (out / "depth.txt").exists() and not overwrite:
            raise RealgapError(f"{out}: exists and is not a sequence folder (choose an empty folder)")
        _copy_sequence(reader, out, cam)
    elif camera is not None:
        write_camera_json(out / "camera.json", cam)
    mark_incomplete(out, "realgap data make-reference", 0, None, unit="frames fused", resumable=False)
    res = fuse_reference(reader, cfg, progress=progress)
    scene = SceneSpec([res.mesh], {cfg.material: Material(float(cfg.albedo), float(cfg.specular))})
    write_scene_json(out, scene)
    res.out_dir = out
    from data_tools.results import atomic_write_json
    atomic_write_json(meta_path, {"source": str(src.resolve()), "config": cfg.to_dict(), "result": res.to_json()})
    clear_incomplete(out)
    return res
