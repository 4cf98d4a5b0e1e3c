"""Fast CPU "photo" renderer: shaded RGB images of posed meshes, with shadows and clutter.

Built on :class:`pixie.geometry.render.Renderer` (Embree ray casting): one primary ray per pixel per object,
z-buffered with :func:`pixie.geometry.render.composite`, flat-shaded with Lambert + Blinn-Phong specular
under 1-3 directional lights and an ambient term, with hard shadows from Embree shadow rays cast
against a scene holding every object of the frame. Colours may be per object or per face (part
colours of an assembly), backgrounds are procedural and :func:`degrade` adds camera effects.

Conventions: OpenCV camera, mm, ``T_cam_from_obj`` poses, colours as floats in [0, 1] (linear),
the output is gamma-encoded (sRGB-like) uint8. A 640x480 frame with a few objects takes
~0.1-0.3 s on one core.

API (kept stable; other modules build training data with it)::

    render_rgb(renderers, poses, K, height, width, materials, rng, background=None, lights=None)
        -> PhotoResult(rgb, depth, owner, masks_visib, masks)
    random_background(h, w, rng) -> (h, w, 3) uint8
    degrade(rgb, rng) -> (h, w, 3) uint8
    Material(color, face_colors=None, roughness=0.5, specular=0.3, albedo_noise=0.0)
    Material.random(rng), Material.from_part_colors(face_part_ids, part_colors, ...)
    LightRig(lights=[DirectionalLight(direction, color, intensity)], ambient)
    LightRig.random(rng)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from pixie.geometry.camera import validate_K, validate_pose
from pixie.geometry.mesh import from_arrays
from pixie.geometry.render import RenderResult, Renderer, composite

__all__ = [
    "Material",
    "DirectionalLight",
    "LightRig",
    "PhotoResult",
    "render_rgb",
    "random_background",
    "random_color",
    "degrade",
    "shadow_mask",
    "box_renderer",
]


# --------------------------------------------------------------------------- materials, lights


def _rgb(c) -> np.ndarray:
    """Colour as float (3,) in [0, 1]; accepts floats in [0, 1] or 0-255 ints."""
    a = np.asarray(c, dtype=np.float64).reshape(-1)
    if a.size == 1:
        a = np.repeat(a, 3)
    if a.size != 3:
        raise ValueError(f"a colour needs 3 components, got {a.size}")
    if a.max() > 1.0 + 1e-9:
        a = a / 255.0
    return np.clip(a, 0.0, 1.0)


def random_color(rng: np.random.Generator, saturated: bool | None = None) -> np.ndarray:
    """A random plausible object colour (linear RGB in [0, 1]): saturated plastics or greys."""
    if saturated is None:
        saturated = rng.random() < 0.75
    if saturated:
        h = rng.random()
        s = rng.uniform(0.5, 1.0)
        v = rng.uniform(0.35, 1.0)
        hsv = np.array([[[h * 179.0, s * 255.0, v * 255.0]]], np.float32)
        srgb = cv2.cvtColor(hsv.astype(np.uint8), cv2.COLOR_HSV2RGB)[0, 0] / 255.0
        return np.clip(srgb.astype(np.float64) ** 2.2, 0, 1)
    g = rng.uniform(0.02, 0.8)
    return np.clip(np.array([g, g, g]) * rng.uniform(0.95, 1.05, 3), 0, 1)


@dataclass
class Material:
    """Surface appearance of one object.

    Attributes
    ----------
    color : (3,) base albedo, linear RGB in [0, 1] (0-255 values are rescaled).
    face_colors : (F, 3) or None
        Per-triangle albedo overriding ``color`` (e.g. the part colours of an assembly).
    roughness : float in [0, 1]; 0 = glossy (sharp highlight), 1 = matte.
    specular : float, strength of the white specular highlight.
    albedo_noise : float, relative amplitude of a smooth per-pixel albedo variation (dirt, print).
    """

    color: np.ndarray = field(default_factory=lambda: np.array([0.6, 0.6, 0.6]))
    face_colors: np.ndarray | None = None
    roughness: float = 0.5
    specular: float = 0.3
    albedo_noise: float = 0.0

    def __post_init__(self) -> None:
        self.color = _rgb(self.color)
        if self.face_colors is not None:
            fc = np.asarray(self.face_colors, dtype=np.float64)
            if fc.ndim != 2 or fc.shape[1] != 3:
                raise ValueError(f"face_colors must be (F, 3), got {fc.shape}")
            if fc.size and fc.max() > 1.0 + 1e-9:
                fc = fc / 255.0
            self.face_colors = np.clip(fc, 0.0, 1.0).astype(np.float32)

    @classmethod
    def random(cls, rng: np.random.Generator, **kw) -> "Material":
        """A random single-colour material (plastic, metal-ish or matte)."""
        args = dict(
            color=random_color(rng),
            roughness=float(rng.uniform(0.15, 0.95)),
            specular=float(rng.uniform(0.05, 0.6)),
            albedo_noise=float(rng.uniform(0.0, 0.15)),
        )
        args.update(kw)
        return cls(**args)

    @classmethod
    def from_part_colors(cls, face_part_ids: np.ndarray, part_colors, **kw) -> "Material":
        """Per-face material from a part index per face and one colour per part."""
        pc = np.stack([_rgb(c) for c in part_colors])
        ids = np.asarray(face_part_ids, dtype=np.int64)
        return cls(color=pc.mean(axis=0), face_colors=pc[ids], **kw)


@dataclass
class DirectionalLight:
    """A light at infinity. ``direction``: unit vector from the surface towards the light, camera frame."""

    direction: np.ndarray
    color: np.ndarray = field(default_factory=lambda: np.ones(3))
    intensity: float = 1.0

    def __post_init__(self) -> None:
        d = np.asarray(self.direction, dtype=np.float64).reshape(3)
        self.direction = d / max(np.linalg.norm(d), 1e-12)
        self.color = _rgb(self.color)


@dataclass
class LightRig:
    """1-3 directional lights plus an ambient term (RGB, linear)."""

    lights: list[DirectionalLight]
    ambient: np.ndarray = field(default_factory=lambda: np.full(3, 0.25))

    def __post_init__(self) -> None:
        self.ambient = _rgb(self.ambient)

    @classmethod
    def random(cls, rng: np.random.Generator, n_lights: int | None = None) -> "LightRig":
        """Lights from the camera's hemisphere (so the visible side is mostly lit), random tints."""
        n = int(rng.integers(1, 4)) if n_lights is None else int(n_lights)
        lights = []
        for i in range(n):
            # Direction towards the light: negative z (towards the camera side), spread sideways.
            az = rng.uniform(0, 2 * np.pi)
            el = rng.uniform(np.radians(15), np.radians(75))  # angle from the image plane
            d = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)])
            tint = 1.0 - rng.uniform(0, 0.15, 3)
            inten = rng.uniform(0.6, 1.1) if i == 0 else rng.uniform(0.15, 0.5)
            lights.append(DirectionalLight(d, tint, float(inten)))
        ambient = rng.uniform(0.12, 0.35) * (1.0 - rng.uniform(0, 0.1, 3))
        return cls(lights, ambient)


@dataclass
class PhotoResult:
    """One synthetic photo.

    rgb : (H, W, 3) uint8
    depth : (H, W) float32, z in mm of the nearest object (0 = background)
    owner : (H, W) int32, index of the object owning each pixel, -1 = background
    masks_visib : list of (H, W) bool, visible pixels of each object (``owner == i``)
    masks : list of (H, W) bool, full silhouette of each object (ignoring occlusion)
    renders : list of RenderResult, the per-object geometry renders
    shadow : (H, W) float32, fraction of the direct light blocked (0 = fully lit), object pixels only
    """

    rgb: np.ndarray
    depth: np.ndarray
    owner: np.ndarray
    masks_visib: list[np.ndarray]
    masks: list[np.ndarray]
    renders: list[RenderResult] = field(default_factory=list, repr=False)
    shadow: np.ndarray | None = field(default=None, repr=False)

    def visib_fract(self, i: int) -> float:
        n = int(self.masks[i].sum())
        return float(self.masks_visib[i].sum()) / n if n else 0.0


def box_renderer(extents, name: str = "distractor") -> Renderer:
    """A renderer of a box with these ``extents`` (mm), centred at its origin: clutter and occluders of scenes."""
    import trimesh

    b = trimesh.creation.box(extents=np.asarray(extents, np.float64))
    return Renderer(from_arrays(np.asarray(b.vertices), np.asarray(b.faces), name=name))


# --------------------------------------------------------------------------- shadows


def _shadow_scene(renderers: list[Renderer], poses: list[np.ndarray]):
    """Embree scene with every object in the camera frame (built per frame: cheap for CAD meshes)."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    scene = rtcore_scene.EmbreeScene()
    for r, T in zip(renderers, poses):
        v = r.mesh.vertices @ T[:3, :3].T + T[:3, 3]
        TriangleMesh(scene=scene, vertices=v.astype(np.float32), indices=r.mesh.faces.astype(np.int32))
    return scene


def shadow_mask(scene, points: np.ndarray, normals: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """True where the ray from ``points`` (N, 3, camera frame) towards ``direction`` hits geometry."""
    if len(points) == 0:
        return np.zeros(0, bool)
    eps = 1e-3 * np.maximum(np.abs(points[:, 2]), 1.0)  # offset relative to depth (float32 BVH)
    org = points + normals * eps[:, None] + direction[None] * eps[:, None]
    dirs = np.broadcast_to(direction.astype(np.float32), org.shape).copy()
    prim = scene.run(org.astype(np.float32), dirs)
    return np.asarray(prim) >= 0


# --------------------------------------------------------------------------- rendering


def _smooth_noise(h: int, w: int, rng: np.random.Generator, scale: float, octaves: int = 4) -> np.ndarray:
    """Multi-octave value noise in roughly [-1, 1], (h, w) float32."""
    out = np.zeros((h, w), np.float32)
    amp, total = 1.0, 0.0
    cell = max(scale, 2.0)
    for _ in range(octaves):
        gh, gw = max(int(np.ceil(h / cell)) + 1, 2), max(int(np.ceil(w / cell)) + 1, 2)
        grid = rng.uniform(-1, 1, (gh, gw)).astype(np.float32)
        out += amp * cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= 0.5
        cell = max(cell / 2.0, 2.0)
    return out / total


def render_rgb(
    renderers: list[Renderer],
    poses: list[np.ndarray],
    K: np.ndarray,
    height: int,
    width: int,
    materials: list[Material],
    rng: np.random.Generator,
    background: np.ndarray | None = None,
    lights: LightRig | None = None,
    shadows: bool = True,
    gamma: float = 2.2,
    renders: list[RenderResult] | None = None,
) -> PhotoResult:
    """Render a shaded RGB photo of several posed objects.

    Parameters
    ----------
    renderers : one :class:`Renderer` per object (the same renderer may appear several times).
    poses : one (4, 4) ``T_cam_from_obj`` per object, mm.
    K : (3, 3) intrinsics; height, width : image size.
    materials : one :class:`Material` per object.
    rng : random generator (background, lights and albedo noise when not given).
    background : (H, W, 3) uint8 image, or None for :func:`random_background`.
    lights : :class:`LightRig`, or None for :meth:`LightRig.random`.
    shadows : cast shadow rays (objects shadow themselves and each other; the background is an
        image and receives none).
    gamma : encoding gamma of the output (linear shading -> display values).
    renders : precomputed ``renderers[i].render(poses[i], K, height, width)`` results (optional,
        saves the geometry pass when the caller already has it).
    """
    if not (len(renderers) == len(poses) == len(materials)):
        raise ValueError(f"need one pose and material per renderer: {len(renderers)}, {len(poses)}, {len(materials)}")
    K = validate_K(K)
    poses = [validate_pose(T) for T in poses]
    if background is None:
        background = random_background(height, width, rng)
    background = np.asarray(background)
    if background.shape != (height, width, 3):
        raise ValueError(f"background must be ({height}, {width}, 3), got {background.shape}")
    if lights is None:
        lights = LightRig.random(rng)

    if renders is None:
        renders = [r.render(T, K, height, width) for r, T in zip(renderers, poses)]
    elif len(renders) != len(renderers):
        raise ValueError(f"need one render per renderer: {len(renders)} != {len(renderers)}")
    if renders:
        depth, owner = composite(renders)
    else:
        depth, owner = np.zeros((height, width), np.float32), np.full((height, width), -1, np.int32)
    rgb = background.astype(np.float32) / 255.0
    shadow_frac = np.zeros((height, width), np.float32)

    fg = np.flatnonzero(owner.ravel() >= 0)
    if len(fg):
        own = owner.ravel()[fg]
        # Per-pixel flat normal, albedo and camera-frame position.
        n_cam = np.zeros((len(fg), 3), np.float32)
        albedo = np.zeros((len(fg), 3), np.float32)
        rough = np.zeros(len(fg), np.float32)
        spec = np.zeros(len(fg), np.float32)
        for i, (r, T, m) in enumerate(zip(renderers, poses, materials)):
            sel = own == i
            if not np.any(sel):
                continue
            tri = renders[i].tri_ids.ravel()[fg[sel]]
            fn = r._fn[tri] @ T[:3, :3].T
            n_cam[sel] = fn
            albedo[sel] = m.face_colors[tri] if m.face_colors is not None else m.color
            if m.albedo_noise > 0:
                noise = _smooth_noise(height, width, rng, scale=rng.uniform(8, 40)).ravel()[fg[sel]]
                albedo[sel] *= np.clip(1.0 + m.albedo_noise * noise, 0.0, 2.0)[:, None]
            rough[sel] = m.roughness
            spec[sel] = m.specular
        rows, cols = np.divmod(fg, width)
        z = depth.ravel()[fg].astype(np.float64)
        p_cam = np.stack([(cols - K[0, 2]) / K[0, 0] * z, (rows - K[1, 2]) / K[1, 1] * z, z], axis=1)
        view = -p_cam / np.linalg.norm(p_cam, axis=1, keepdims=True)  # towards the camera
        flip = np.einsum("ij,ij->i", n_cam, view) < 0
        n_cam[flip] *= -1
        n64 = n_cam.astype(np.float64)
        shininess = 2.0 + (1.0 - rough.astype(np.float64)) ** 2 * 250.0
        color = albedo * lights.ambient[None].astype(np.float32)
        scene = _shadow_scene(renderers, poses) if shadows and lights.lights else None
        total_int = sum(L.intensity for L in lights.lights) or 1.0
        for L in lights.lights:
            ndl = n64 @ L.direction
            lit = ndl > 0
            if scene is not None and np.any(lit):
                occl = np.zeros(len(fg), bool)
                idx = np.flatnonzero(lit)
                occl[idx] = shadow_mask(scene, p_cam[idx], n64[idx], L.direction)
                shadow_frac.ravel()[fg[occl]] += L.intensity / total_int
                lit &= ~occl
            h_vec = L.direction[None] + view
            h_vec /= np.maximum(np.linalg.norm(h_vec, axis=1, keepdims=True), 1e-12)
            ndh = np.clip(np.einsum("ij,ij->i", n64, h_vec), 0, 1)
            specular = spec * (ndh**shininess) * (shininess + 8) / (8 * np.pi) * 0.5
            diffuse = np.clip(ndl, 0, None)
            contrib = (albedo * diffuse[:, None] + specular[:, None]) * (L.intensity * L.color)[None]
            color += np.where(lit[:, None], contrib, 0.0).astype(np.float32)
        color = np.clip(color, 0, 1) ** (1.0 / gamma)
        rgb.reshape(-1, 3)[fg] = color
    # Slight anti-aliasing of object borders: blend a 1-px blurred copy on silhouette edges.
    if len(fg):
        edge = cv2.morphologyEx((owner + 1).astype(np.uint16), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
        blurred = cv2.GaussianBlur(rgb, (3, 3), 0.7)
        rgb[edge] = blurred[edge]
    out = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
    masks_visib = [owner == i for i in range(len(renders))]
    masks = [r.mask for r in renders]
    return PhotoResult(out, depth, owner, masks_visib, masks, renders, shadow_frac)


# --------------------------------------------------------------------------- backgrounds


def random_background(h: int, w: int, rng: np.random.Generator, kind: str | None = None) -> np.ndarray:
    """A procedural background (H, W, 3) uint8.

    kind : 'gradient', 'noise', 'texture' (stripes / checker / wood-like), 'clutter'
        (random shapes over noise) or None for a random choice.
    """
    kinds = ("gradient", "noise", "texture", "clutter")
    kind = kinds[int(rng.integers(len(kinds)))] if kind is None else kind
    c0, c1 = random_color(rng) ** (1 / 2.2), random_color(rng) ** (1 / 2.2)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    if kind == "gradient":
        a = rng.uniform(0, 2 * np.pi)
        t = (np.cos(a) * xx / w + np.sin(a) * yy / h)
        t = (t - t.min()) / max(float(t.max() - t.min()), 1e-6)
        img = c0[None, None] * (1 - t[..., None]) + c1[None, None] * t[..., None]
        img = img * (1 + 0.05 * _smooth_noise(h, w, rng, 64)[..., None])
    elif kind == "noise":
        n = _smooth_noise(h, w, rng, rng.uniform(16, 160), octaves=5)
        t = np.clip(0.5 + 0.8 * n, 0, 1)[..., None]
        img = c0[None, None] * (1 - t) + c1[None, None] * t
    elif kind == "texture":
        a = rng.uniform(0, np.pi)
        u = np.cos(a) * xx + np.sin(a) * yy
        v = -np.sin(a) * xx + np.cos(a) * yy
        period = rng.uniform(8, 60)
        style = int(rng.integers(3))
        if style == 0:  # stripes
            t = 0.5 + 0.5 * np.sin(2 * np.pi * u / period)
        elif style == 1:  # checker
            t = ((np.floor(u / period) + np.floor(v / period)) % 2).astype(np.float32)
        else:  # wood-like grain
            warp = 12 * _smooth_noise(h, w, rng, 80)
            t = 0.5 + 0.5 * np.sin(2 * np.pi * (u + warp) / (period * 0.4))
        t = np.clip(t + 0.15 * _smooth_noise(h, w, rng, 20), 0, 1)[..., None]
        img = c0[None, None] * (1 - t) + c1[None, None] * t
    elif kind == "clutter":
        n = _smooth_noise(h, w, rng, 80)
        img = c0[None, None] * (0.8 + 0.2 * n[..., None])
        img = np.ascontiguousarray(img.astype(np.float32))
        for _ in range(int(rng.integers(5, 25))):
            col = tuple(float(x) for x in random_color(rng) ** (1 / 2.2))
            cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
            s = int(rng.uniform(0.03, 0.25) * max(h, w))
            if rng.random() < 0.5:
                cv2.rectangle(img, (cx - s, cy - s // 2), (cx + s, cy + s // 2), col, -1)
            else:
                cv2.ellipse(img, (cx, cy), (s, max(s // 2, 1)), float(rng.uniform(0, 180)), 0, 360, col, -1)
        img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.5, 2.5))
    else:
        raise ValueError(f"unknown background kind {kind!r}; use one of {kinds}")
    return np.clip(np.asarray(img) * 255.0 + 0.5, 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- post-effects


def degrade(
    rgb: np.ndarray,
    rng: np.random.Generator,
    blur: bool | None = None,
    noise: bool | None = None,
    jpeg: bool | None = None,
    resample: bool | None = None,
) -> np.ndarray:
    """Camera-like post-effects on a uint8 RGB image; each is applied with probability 1/2
    unless forced with True/False: down/up-sampling, Gaussian blur, sensor noise (shot + read),
    white-balance jitter and JPEG compression. Output: uint8 of the same shape."""
    img = np.asarray(rgb)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"degrade needs an (H, W, 3) uint8 image, got {img.shape} {img.dtype}")
    h, w = img.shape[:2]

    def on(flag):
        return bool(rng.random() < 0.5) if flag is None else bool(flag)

    out = img.astype(np.float32)
    if on(resample):
        f = rng.uniform(0.4, 0.9)
        small = cv2.resize(out, (max(int(w * f), 1), max(int(h * f), 1)), interpolation=cv2.INTER_AREA)
        out = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    if on(blur):
        out = cv2.GaussianBlur(out, (0, 0), rng.uniform(0.4, 1.5))
    # White balance / exposure jitter (always mild).
    out = out * rng.uniform(0.9, 1.1, 3)[None, None].astype(np.float32) * np.float32(rng.uniform(0.85, 1.15))
    if on(noise):
        lam = rng.uniform(0.02, 0.12)  # shot noise scale
        read = rng.uniform(0.5, 5.0)
        sigma = np.sqrt(np.clip(out, 0, 255) * lam + read**2)
        out = out + rng.standard_normal(out.shape).astype(np.float32) * sigma.astype(np.float32)
    out = np.clip(out + 0.5, 0, 255).astype(np.uint8)
    if on(jpeg):
        q = int(rng.integers(30, 95))
        ok, buf = cv2.imencode(".jpg", out[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, q])
        if ok:
            out = np.ascontiguousarray(cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1])
    return out
