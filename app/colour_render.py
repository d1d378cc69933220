"""The renderer of SynDA's colour test sets (:mod:`recog.synda.colour_testset`): VTK through PyVista, off
screen (EGL or OSMesa, whatever the VTK build has), so it lives in app/ (pyvista is app/'s alone).

It renders a :class:`recog.synda.colour_testset.ColourScene` in the camera frame (OpenCV: x right, y down,
z forward; VTK's camera at the origin looking along +z with -y up, vertical view angle
``2 atan(H / 2 f)``): the object with an image texture (spherical or planar texture coordinates
computed in the object's own frame, so the texture sticks to the object), Phong or physically based
material, 1-3 coloured directional lights (VTK scene lights shining from the drawn position onto the
object) and the occluding solids. Returns the RGBA image (alpha 0 where nothing was drawn, for the
background photograph), the depth (camera z from the z-buffer, metres, 0 = nothing) and the object's
visible pixels (its depth alone equals the scene's, within 1 mm).

Approximation: the principal point is the image centre (VTK's camera has none other without an
explicit projection matrix); the colour test set's camera.json says so.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from recog.objects import RecogObject
from recog.synda.colour_testset import ColourScene, ColourTestsetConfig

__all__ = ["PyVistaRenderer"]

VISIBLE_TOL_M = 1e-3
"""A pixel shows the object when the object's own depth and the scene's differ by less than this."""


class PyVistaRenderer:
    """``render(scene, obj) -> (rgba, depth, visible mask)`` for :func:`recog.synda.colour_testset.make_colour_testset`."""

    def __init__(self, cfg: ColourTestsetConfig, textures: list[Path]):
        import pyvista as pv

        from app.viewer.window import quiet_vtk_warnings
        pv.OFF_SCREEN = True
        quiet_vtk_warnings()          # no "bad X server connection" line per run: EGL renders off screen
        self.cfg = cfg
        self.texture_files = list(textures)
        self._textures: dict[int, object] = {}
        self._meshes: dict[tuple[str, str], object] = {}

    def texture(self, i: int):
        import pyvista as pv

        from data_tools.sequence import read_rgb_image
        if i not in self._textures:
            self._textures[i] = pv.Texture(read_rgb_image(self.texture_files[i]))
        return self._textures[i]

    def object_mesh(self, obj: RecogObject, mapping: str):
        """The object's merged mesh (object frame) with texture coordinates of ``mapping``."""
        import pyvista as pv
        key = (obj.name, mapping)
        if key not in self._meshes:
            m = obj.merged()
            faces = np.hstack([np.full((len(m.triangles), 1), 3), m.triangles]).astype(np.int64).ravel()
            poly = pv.PolyData(np.asarray(m.vertices, float), faces)
            if mapping == "sphere":
                poly.texture_map_to_sphere(inplace=True)
            else:
                poly.texture_map_to_plane(inplace=True)
            self._meshes[key] = poly
        return self._meshes[key]

    def __call__(self, scene: ColourScene, obj: RecogObject):
        import pyvista as pv
        cfg = self.cfg
        p = pv.Plotter(off_screen=True, window_size=(cfg.width, cfg.height), lighting="none")
        try:
            p.set_background("black")
            mesh = self.object_mesh(obj, scene.mapping).transform(np.asarray(scene.pose, float), inplace=False)
            mat = scene.material
            kw = dict(pbr=True, metallic=mat["metallic"], roughness=mat["roughness"]) if mat["pbr"] else \
                dict(ambient=mat["ambient"], diffuse=mat["diffuse"], specular=mat["specular"],
                     specular_power=mat["specular_power"])
            p.add_mesh(mesh, texture=self.texture(scene.texture), smooth_shading=True, **kw)
            centre = np.asarray(scene.pose, float)[:3, 3]
            for li in scene.lights:
                p.add_light(pv.Light(position=tuple(np.asarray(li["position"], float)), focal_point=tuple(centre),
                                     color=tuple(np.asarray(li["colour"], float)), intensity=li["intensity"],
                                     light_type="scene light"))
            cam = p.camera
            cam.position, cam.focal_point, cam.up = (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0)
            cam.view_angle = math.degrees(2 * math.atan(cfg.height / 2 / cfg.focal_px))
            cam.clipping_range = (0.02, 100.0)
            obj_depth = self._depth(p)
            for o in scene.occluders:
                solid = _solid(o["shape"], o["size"])
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = o["rotation"], o["centre"]
                solid = solid.transform(T, inplace=False)
                if o["texture"] >= 0:
                    solid.texture_map_to_sphere(inplace=True)
                    p.add_mesh(solid, texture=self.texture(o["texture"]), ambient=0.15, diffuse=0.8, specular=0.2)
                else:
                    p.add_mesh(solid, color=tuple(np.asarray(o["colour"], float)), ambient=0.15, diffuse=0.8,
                               specular=0.3, specular_power=20)
            rgba = np.asarray(p.screenshot(transparent_background=True, return_img=True), np.uint8)
            depth = self._depth(p) if scene.occluders else obj_depth
        finally:
            p.close()
        visible = (obj_depth > 0) & (np.abs(depth - obj_depth) < VISIBLE_TOL_M)
        return rgba, depth, visible

    @staticmethod
    def _depth(p) -> np.ndarray:
        """(H, W) camera z of the current scene, metres; 0 where nothing is drawn."""
        if getattr(p, "_rendered", False):
            p.render()
        else:
            p.show(auto_close=False)
        d = np.asarray(p.get_image_depth(fill_value=np.nan, reset_camera_clipping_range=False), np.float64)
        return np.where(np.isfinite(d), -d, 0.0).astype(np.float32)


def _solid(shape: str, size: float):
    import pyvista as pv
    if shape == "sphere":
        return pv.Sphere(radius=size / 2, theta_resolution=24, phi_resolution=24)
    if shape == "box":
        return pv.Cube(x_length=size, y_length=0.7 * size, z_length=0.5 * size).triangulate()
    if shape == "cylinder":
        return pv.Cylinder(radius=size / 4, height=size, resolution=24).triangulate()
    if shape == "cone":
        return pv.Cone(radius=size / 3, height=size, resolution=24).triangulate()
    raise ValueError(f"unknown occluder shape {shape!r}")
