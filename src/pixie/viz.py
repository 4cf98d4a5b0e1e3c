"""Pictures for people: reference contact sheets, pose overlays, match drawings."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from pixie.geometry.camera import project
from pixie.references.encode import shade
from pixie.paths import write_atomic
from pixie.references.set import ReferenceSet, encoding_images
from pixie.geometry.render import Renderer
from pixie.pose.results import SUSPECT_VERDICTS

EST_COLOR = (255, 40, 40)
GT_COLOR = (40, 220, 40)


def _rgb(img: np.ndarray) -> np.ndarray:
    return np.repeat(img[..., None], 3, axis=2) if img.ndim == 2 else img


def draw_contours(rgb: np.ndarray, mask: np.ndarray, color: tuple[int, int, int], thickness: int = 2) -> np.ndarray:
    """Draw the outer contours of a boolean mask on a copy of an RGB image."""
    out = rgb.copy()
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, color, thickness, lineType=cv2.LINE_AA)
    return out


def contact_sheet(refs: ReferenceSet, encodings: list[str] | None = None, views: list[int] | None = None,
                  tile: int = 128, columns: int = 11) -> np.ndarray:
    """A grid of roll-0 reference images: one block of rows per encoding, labelled with the view index."""
    encodings = encodings or list(refs.config.encodings)
    views = views if views is not None else list(range(refs.n_views))
    blocks = []
    for e in encodings:
        imgs = encoding_images(refs, e)
        tiles = []
        for v in views:
            t = cv2.resize(_rgb(imgs[v]), (tile, tile), interpolation=cv2.INTER_AREA)
            cv2.putText(t, f"{v}", (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 0), 1, cv2.LINE_AA)
            tiles.append(t)
        while len(tiles) % columns:
            tiles.append(np.zeros_like(tiles[0]))
        rows = [np.concatenate(tiles[i:i + columns], axis=1) for i in range(0, len(tiles), columns)]
        header = np.zeros((22, rows[0].shape[1], 3), np.uint8)
        cv2.putText(header, f"{refs.mesh.name}: {e}", (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        blocks.append(np.concatenate([header, *rows], axis=0))
    return np.concatenate(blocks, axis=0)


def overlay_pose(image: np.ndarray, renderer: Renderer, T_est: np.ndarray | None, K: np.ndarray,
                 T_gt: np.ndarray | None = None, shade_alpha: float = 0.35) -> np.ndarray:
    """The model drawn at the estimate (shaded, red contour) and optionally at GT (green contour)."""
    h, w = image.shape[:2]
    out = _rgb(image).copy()
    if T_est is not None:
        r = renderer.render(T_est, K, h, w)
        s = shade(r.normals, r.mask, 3)
        tint = np.stack([s, (s * 0.5).astype(np.uint8), (s * 0.5).astype(np.uint8)], axis=-1)
        out[r.mask] = ((1 - shade_alpha) * out[r.mask] + shade_alpha * tint[r.mask]).astype(np.uint8)
        out = draw_contours(out, r.mask, EST_COLOR)
    if T_gt is not None:
        out = draw_contours(out, renderer.render(T_gt, K, h, w).mask, GT_COLOR)
    return out


BOX_COLOR = (255, 220, 0)
AXIS_COLORS = ((230, 30, 30), (30, 200, 30), (40, 90, 255))  # x red, y green, z blue


def line_width(mask_or_box: np.ndarray, per_px: float = 120.0) -> int:
    """Line width for drawings on an object: 1 px up to ~120 px across, growing slowly, at most 4."""
    b = np.asarray(mask_or_box)
    if b.dtype == bool:
        ys, xs = np.nonzero(b)
        side = max(np.ptp(xs), np.ptp(ys)) + 1 if len(xs) else 0
    else:
        side = max(b[2] - b[0], b[3] - b[1])
    return int(np.clip(round(side / per_px), 1, 4))


def overlay_result(image: np.ndarray, renderer: Renderer, T: np.ndarray | None, K: np.ndarray,
                   box_xyxy: np.ndarray | None = None, label: str | None = None,
                   T_gt: np.ndarray | None = None, shade_alpha: float = 0.3) -> np.ndarray:
    """A picture of one estimate for people: model contour (red) and light shading at ``T``, the object's
    axes at its origin (x red, y green, z blue, 0.3 diameters long), the given box (yellow) and ``label``
    (e.g. the confidence). Line widths scale with the object's size in the image.
    """

    h, w = image.shape[:2]
    out = _rgb(image).copy()
    ref = box_xyxy
    if T is not None:
        r = renderer.render(T, K, h, w)
        lw = line_width(r.mask if r.mask.any() else (box_xyxy if box_xyxy is not None else np.array([0, 0, 60, 60])))
        if r.mask.any():
            s = shade(r.normals, r.mask, 3)
            tint = np.stack([s, (s * 0.5).astype(np.uint8), (s * 0.5).astype(np.uint8)], axis=-1)
            out[r.mask] = ((1 - shade_alpha) * out[r.mask] + shade_alpha * tint[r.mask]).astype(np.uint8)
            out = draw_contours(out, r.mask, EST_COLOR, lw)
        L = 0.3 * renderer.mesh.diameter
        pts = np.array([[0, 0, 0], [L, 0, 0], [0, L, 0], [0, 0, L]], np.float64)
        cam = pts @ T[:3, :3].T + T[:3, 3]
        if np.all(cam[:, 2] > 1e-6):
            uv = project(K, cam)
            if np.all(np.isfinite(uv)) and np.all(np.abs(uv) < 1e5):
                o = tuple(int(round(v)) for v in uv[0])
                for k in range(3):
                    cv2.arrowedLine(out, o, tuple(int(round(v)) for v in uv[k + 1]), AXIS_COLORS[k], lw,
                                    cv2.LINE_AA, tipLength=0.15)
    else:
        lw = line_width(box_xyxy) if box_xyxy is not None else 1
    if T_gt is not None:
        out = draw_contours(out, renderer.render(T_gt, K, h, w).mask, GT_COLOR, lw)
    if ref is not None:
        x0, y0, x1, y1 = (int(round(v)) for v in ref)
        cv2.rectangle(out, (x0, y0), (x1 - 1, y1 - 1), BOX_COLOR, max(1, lw - 1), cv2.LINE_AA)
    if label:
        scale = max(0.4, min(1.0, h / 900))
        org = (int(ref[0]) if ref is not None else 4, max(14, int(ref[1]) - 5) if ref is not None else 18)
        cv2.putText(out, label, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(out, label, org, cv2.FONT_HERSHEY_SIMPLEX, scale, BOX_COLOR, 1, cv2.LINE_AA)
    return out


VERDICT_COLORS = {"present": (40, 200, 60), "missing": (235, 30, 30), "displaced": (255, 150, 0),
                  "wrong": (200, 40, 220), "not visible": (150, 150, 150)}


def draw_parts(image: np.ndarray, parts, radius: int = 1) -> np.ndarray:
    """The part report drawn on ``image``: every part's contour points coloured by its verdict (present green,
    missing red, displaced orange, wrong magenta, not visible grey) and the suspect parts' names next to them.

    ``parts``: :class:`pixie.cues.parts.PartSupport` records (``uv`` photo px, ``verdict``, ``name``).
    """
    out = _rgb(image).copy()
    for p in sorted(parts, key=lambda p: p.verdict in SUSPECT_VERDICTS):  # suspects drawn last (on top)
        col = VERDICT_COLORS.get(p.verdict, (255, 255, 255))
        for u, v in np.rint(np.asarray(p.uv)).astype(int):
            cv2.circle(out, (int(u), int(v)), radius, col, -1)
    h = out.shape[0]
    scale = max(0.35, min(0.8, h / 1200))
    for p in parts:
        if p.verdict in SUSPECT_VERDICTS and len(p.uv):
            u, v = np.asarray(p.uv).mean(axis=0)
            org = (int(u) + 4, int(v))
            moved = (getattr(p, "move", "") if p.verdict == "displaced" and getattr(p, "move_gain", 0.0) > 0
                     else getattr(p, "size", "") if p.verdict == "wrong" else "")
            text = f"{p.name}: {p.verdict}" + (f" ({moved})" if moved else "")
            cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
            cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, VERDICT_COLORS[p.verdict], 1, cv2.LINE_AA)
    return out


def status_view(overlay: np.ndarray, box_xyxy: np.ndarray | None, failed: bool, message: str = "",
                detail: str = "", zoom_frac: float = 0.4) -> np.ndarray:
    """The overlay with what a person needs at a glance: a banner on top (green "OK" or red "FAILED: reason",
    then ``detail``, e.g. the confidence and translation) and, for an object smaller than a third of the image, a
    zoomed inset of its box region (at most ``zoom_frac`` of the image width) in the corner farthest from it."""
    img = _rgb(overlay)
    h, w = img.shape[:2]
    out = img.copy()
    if box_xyxy is not None:
        x0, y0, x1, y1 = (float(v) for v in box_xyxy)
        bw, bh = max(x1 - x0, 1.0), max(y1 - y0, 1.0)
        if max(bw / w, bh / h) < 1 / 3:
            pad = 0.25 * max(bw, bh)
            cx, cy, half = (x0 + x1) / 2, (y0 + y1) / 2, max(bw, bh) / 2 + pad
            xa, ya = int(max(cx - half, 0)), int(max(cy - half, 0))
            xb, yb = int(min(cx + half, w)), int(min(cy + half, h))
            crop = img[ya:yb, xa:xb]
            if crop.size:
                side = int(zoom_frac * min(w, h))
                f = side / max(crop.shape[:2])
                inset = cv2.resize(crop, (max(int(crop.shape[1] * f), 1), max(int(crop.shape[0] * f), 1)),
                                   interpolation=cv2.INTER_NEAREST if f >= 2 else cv2.INTER_LINEAR)
                ih, iw = inset.shape[:2]
                # the corner farthest from the object
                left = cx > w / 2
                top = cy > h / 2
                ox, oy = (4 if left else w - iw - 4), (4 if top else h - ih - 4)
                out[oy:oy + ih, ox:ox + iw] = inset
                cv2.rectangle(out, (ox - 1, oy - 1), (ox + iw, oy + ih), (255, 255, 255), 1)
    bar_h = max(24, h // 16)
    scale = bar_h / 40
    colour = (200, 30, 30) if failed else (30, 150, 60)
    head = f"FAILED: {message}" if failed else "OK"
    banner = np.full((bar_h, w, 3), colour, np.uint8)
    text = head + (f"   {detail}" if detail else "")
    th = max(1, int(round(2 * scale)))
    tw = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, th)[0][0]
    if tw > w - 12:  # shrink to fit the width (down to a readable minimum), then cut
        scale = max(scale * (w - 12) / tw, 0.35)
        th = max(1, int(round(2 * scale)))
        while len(text) > 8 and cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, th)[0][0] > w - 12:
            text = text[:-2]
    cv2.putText(banner, text, (6, int(bar_h * 0.72)), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), th, cv2.LINE_AA)
    return np.concatenate([banner, out], axis=0)


def pose_detail(res, gt_error: dict | None = None) -> str:
    """One line for the banner: confidence, the translation (mm) and, with a ground truth, the errors."""
    parts = [f"confidence {res.confidence:.2f}"]
    if res.T_cam_from_obj is not None:
        parts.append("t = (" + ", ".join(f"{v:.0f}" for v in res.T_cam_from_obj[:3, 3]) + ") mm")
    if gt_error:
        parts.append(f"vs GT {gt_error['rot_deg']:.1f} deg, {gt_error['trans_mm']:.1f} mm")
    return ", ".join(parts)


def encode_png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an RGB (or grey) image."""
    ok, buf = cv2.imencode(".png", _rgb(rgb)[..., ::-1])
    if not ok:
        raise OSError("cannot encode PNG")
    return buf.tobytes()


def draw_matches(img_q: np.ndarray, img_r: np.ndarray, kq: np.ndarray, kr: np.ndarray,
                 inliers: np.ndarray | None = None, max_lines: int = 200) -> np.ndarray:
    """Side-by-side query / reference with match lines (green inliers, red others)."""
    a, b = _rgb(img_q), _rgb(img_r)
    h = max(a.shape[0], b.shape[0])
    canvas = np.zeros((h, a.shape[1] + b.shape[1], 3), np.uint8)
    canvas[: a.shape[0], : a.shape[1]] = a
    canvas[: b.shape[0], a.shape[1]:] = b
    inl = np.zeros(len(kq), bool) if inliers is None else np.isin(np.arange(len(kq)), inliers)
    step = max(1, len(kq) // max_lines)
    for i in range(0, len(kq), step):
        p = tuple(int(round(x)) for x in kq[i])
        q = (int(round(kr[i][0])) + a.shape[1], int(round(kr[i][1])))
        cv2.line(canvas, p, q, (40, 220, 40) if inl[i] else (220, 40, 40), 1, cv2.LINE_AA)
    return canvas


def save_png(path: str | Path, rgb: np.ndarray, force: bool = True) -> Path:
    """Write an RGB (or grey) image as PNG at exactly ``path`` (whatever its suffix), atomically, creating the folder;
    without ``force`` an existing file is refused (:func:`pixie.paths.write_atomic`)."""

    return write_atomic(path, encode_png(rgb), force=force)
