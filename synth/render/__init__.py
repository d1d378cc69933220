"""Ideal (noise-free) rendering of a scene: :class:`~synth.render.ideal.IdealRenderer` (depth, normals,
instance ids, shaded colour; Open3D ray casting for arbitrary rays) and its exact numba rasteriser
:class:`~synth.render.raster.Rasterizer` (the default back-end of ``IdealRenderer.render``)."""
from synth.render.ideal import IdealRenderer, RenderResult, build_raycasting_scene, pinhole_ray_dirs, shade_rgb

__all__ = ["IdealRenderer", "RenderResult", "build_raycasting_scene", "pinhole_ray_dirs", "shade_rgb"]
