"""Representations study: a surface's bumps stored as a tangent-space normal map (8 and 16
bits, two channels, BC5), a derivative map, a height map differenced in screen space, or an
object-space map; then filtered, blended and shipped as engines do. How far is each from the
truth, and what does it cost?

    python -m scripts.studies.study_representations --out DIR [--quick] [--map PNG]

The surface is a plane seen head-on carrying a tileable height field made of sinusoids
(`height`, analytic gradient, float64 truth). Each representation is built from it at
``--size`` texels, stored as that representation stores it, sampled with jaxnm's GL sampler
(`jaxnm.sample`, trilinear on the representation's mip chain) and decoded to a normal:

- **magnification** (``8`` pixels per texel): the error against the analytic normal at each
  pixel, and the 99th percentile of the angle between neighbouring pixels (a blocky field
  jumps at texel borders); the figure shows a crop lit from a grazing light;
- **minification** (``1 .. 16`` texels per pixel, the mip levels): the error against the
  normalised footprint average of the analytic normals;
- **blending**: a fine detail field laid over the base, each method of `jaxnm.blend` against
  the float64 normal of the summed height fields, and each representation's own blend;
- **storage**: bytes per texel, and the BC5 / DXT5nm encoders compared (`jaxnm.storage`);
- **specular aliasing**: Blinn-Phong highlights of the map at distances, each filtering choice
  (no mip-maps, renormalised and shortened mips, Toksvig, LEAN) against a supersampled
  reference (at least 4x4 level-0 samples a pixel, two a texel);
- **speed**: the median ms of sampling and decoding one 256x256 view with each (CPU);
- **a fit through storage**: on the built-in fitting problem, a map fitted through BC5
  blocks (and through 8-bit codes) by `jaxnm.fit.fit_stored_map` against the float map
  compressed afterwards by quicktex (or rounded): the shading loss and the angular error of
  each *as stored*.

Writes ``representations.json`` and the figures ``fig_magnification.png``,
``fig_minification.png``, ``fig_blend.png``, ``fig_storage.png``, ``fig_specular.png`` and
``fig_stored.png`` into ``--out``. ``--quick`` (CI) runs a 128-texel map, smaller views and
fewer distances, and leaves out the fit through storage (``tests/test_stored_fit.py`` runs
a small one).
``--map PNG`` adds a tangent-space normal map of yours (8-bit RGB, a multiple of 4 texels on
each side) to the encoder comparison.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxnm
from jaxnm import filtering as FL
from jaxnm import io as jio
from jaxnm.blend import BLEND_METHODS, blend_normal_maps, normal_from_gradient
from jaxnm.maps import bump_normal
from jaxnm.textures import build_mipmaps, decode_normal_map, encode_normal_map, quantize
from scripts._cli import output, run_script
from scripts.benchmarks.timing import side_by_side, time_call

TAU = 2 * np.pi
#: The base height field: (amplitude, cycles along u, cycles along v, phase); the plane's
#: texture spans one world unit, so slopes are amplitude * 2 pi * frequency.
BASE_TERMS = ((0.012, 3, 2, 0.3), (0.006, 7, -5, 1.1), (0.003, 13, 11, 2.0),
              (0.0015, 29, 23, 0.5))
#: The detail field laid over it in the blending section.
DETAIL_TERMS = ((0.0012, 37, 31, 0.7), (0.0008, -43, 41, 1.9))
REPRESENTATIONS = ("tangent8", "tangent16", "two_channel8", "bc5", "derivative8",
                   "height_coarse", "height_fine", "object8")
#: Bytes per texel of level 0 as each representation is stored here.
BYTES_PER_TEXEL = {"tangent8": 3, "tangent16": 6, "two_channel8": 2, "bc5": 1,
                   "derivative8": 2, "height_coarse": 2, "height_fine": 2, "object8": 3}
FILTER_CHOICES = ("no_mips", "renormalized", "shortened", "toksvig", "lean")
SHININESS = 64.0
HALF = np.array([np.sin(np.radians(20.0)), 0.0, np.cos(np.radians(20.0))])
#: The object-space map's surface orientation: the plane's frame rotated (object = R tangent).
_A, _B = np.radians(35.0), np.radians(50.0)
ROTATION = (np.array([[np.cos(_B), -np.sin(_B), 0], [np.sin(_B), np.cos(_B), 0], [0, 0, 1]])
            @ np.array([[1, 0, 0], [0, np.cos(_A), -np.sin(_A)], [0, np.sin(_A), np.cos(_A)]]))


# ---------------------------------------------------------------------- the truth


def height(u, v, terms=BASE_TERMS):
    """``(h, grad h)`` of a sum of periodic sinusoids at uv (float64; uv in world units)."""
    u, v = np.asarray(u, np.float64), np.asarray(v, np.float64)
    h = np.zeros(np.broadcast(u, v).shape)
    g = np.zeros(h.shape + (2,))
    for a, fu, fv, ph in terms:
        t = TAU * (fu * u + fv * v) + ph
        h += a * np.sin(t)
        c = a * TAU * np.cos(t)
        g[..., 0] += c * fu
        g[..., 1] += c * fv
    return h, g


def truth_normal(u, v, terms=BASE_TERMS):
    """The analytic unit normal (float64) of the height field at uv."""
    g = height(u, v, terms)[1]
    n = np.concatenate([-g, np.ones_like(g[..., :1])], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def texel_uv(size: int):
    """(u, v) of the texel centres, image layout (row 0 at the top: v near 1)."""
    c = (np.arange(size) + 0.5) / size
    return np.meshgrid(c, 1.0 - c, indexing="xy")


def angle(a, b):
    """Degrees between vectors (float64)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))


def _stats(err) -> dict:
    err = np.asarray(err, np.float64).ravel()
    return {"mean": float(err.mean()), "p95": float(np.percentile(err, 95)),
            "max": float(err.max())}


# ---------------------------------------------------------------------- views


#: Where the minified views' pixels start, in pixels: off the texel grid of every level, as a
#: surface in a scene is (a footprint aligned with a level's texels is filtered exactly).
SHIFT = (0.37, 0.61)


def view(pixels: int, texels_per_pixel: float, size: int, origin=(0.3125, 0.4375),
         shift=(0.0, 0.0)):
    """A head-on view of the plane: ``(uv, duvdx, duvdy, world units per pixel)``, uv
    (pixels, pixels, 2) float32 (image rows from the top; window y up). With no ``shift``
    (in pixels) the pixel centres of a one-texel-a-pixel view sit on texel centres."""
    step = texels_per_pixel / size
    j = np.arange(pixels) + 0.5
    u, v = np.meshgrid(origin[0] + (j + shift[0]) * step, origin[1] + (j[::-1] + shift[1]) * step,
                       indexing="xy")
    uv = np.stack([u, v], -1)
    dx = np.broadcast_to(np.float32([step, 0.0]), uv.shape)
    dy = np.broadcast_to(np.float32([0.0, step]), uv.shape)
    return uv.astype(np.float32), np.ascontiguousarray(dx), np.ascontiguousarray(dy), step


def footprint_truth(uv, step, ss: int, terms=BASE_TERMS):
    """The normalised average of the analytic normals over each pixel's square footprint
    (``ss`` x ``ss`` samples, float64)."""
    o = (np.arange(ss) + 0.5) / ss - 0.5
    ou, ov = np.meshgrid(o * step, o * step, indexing="xy")
    u = np.asarray(uv[..., 0], np.float64)[..., None, None] + ou
    v = np.asarray(uv[..., 1], np.float64)[..., None, None] + ov
    n = truth_normal(u, v, terms).mean((-3, -2))
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


# ---------------------------------------------------------------------- representations


def _quantize_signed(x, scale, bits):
    """x in [-scale, scale] stored as ``bits``-bit unorm codes, and decoded back."""
    return (np.asarray(quantize((x / scale + 1) / 2, bits)) * 2 - 1) * scale


def build(rep: str, size: int, terms=BASE_TERMS, *, encoder: str = "quicktex") -> dict:
    """One representation of the height field: its stored level 0 as floats (``tex``) and
    what its decoder needs."""
    u, v = texel_uv(size)
    h, g = height(u, v, terms)
    n = truth_normal(u, v, terms).astype(np.float32)
    out = {"rep": rep}
    if rep in ("tangent8", "tangent16"):
        bits = 8 if rep == "tangent8" else 16
        out["tex"] = np.asarray(quantize(encode_normal_map(n), bits))
    elif rep in ("two_channel8", "bc5"):
        codes = np.asarray(quantize(encode_normal_map(n, channels=2), 8))
        if rep == "bc5":
            from jaxnm import storage

            c8 = np.round(codes * 255).astype(np.uint8)
            blocks = storage.encode_blocks(c8, format="bc5", encoder=encoder)
            codes = storage.decode_blocks(blocks, (size, size)).astype(np.float32) / 255
        out["tex"] = codes
    elif rep == "derivative8":
        scale = float(np.abs(g).max())
        out["scale"] = scale
        out["tex"] = _quantize_signed(g, scale, 8).astype(np.float32)
    elif rep in ("height_coarse", "height_fine"):
        lo, hi = float(h.min()), float(h.max())
        out["tex"] = (np.asarray(quantize((h - lo) / (hi - lo), 16)) * (hi - lo) + lo)[..., None]
        out["tex"] = out["tex"].astype(np.float32)
    elif rep == "object8":
        obj = np.einsum("ij,...j->...i", ROTATION, n.astype(np.float64)).astype(np.float32)
        out["tex"] = np.asarray(quantize(encode_normal_map(obj), 8))
    else:
        raise ValueError(f"unknown representation {rep!r}")
    out["mips"] = build_mipmaps(jnp.asarray(out["tex"]))
    return out


def _quad_differences(x: np.ndarray | jax.Array, fine: bool):
    """GL's screen-space derivatives of a per-pixel value (image rows from the top, window y
    up) within 2x2 quads: ``fine`` (each row and column its own difference) or coarse (one
    difference per quad: the quad's bottom row for ddx, its left column for ddy)."""
    x = jnp.asarray(x)
    hgt, wid = x.shape
    q = x.reshape(hgt // 2, 2, wid // 2, 2)  # (quad row, row in quad from top, quad col, col)
    ddx = q[:, :, :, 1] - q[:, :, :, 0]  # (qr, 2, qc)
    ddy = q[:, 0] - q[:, 1]  # window y up: the quad's top row minus its bottom row
    if not fine:
        ddx = jnp.broadcast_to(ddx[:, 1:2], ddx.shape)  # the bottom row's
        ddy = jnp.broadcast_to(ddy[:, :, 0:1], ddy.shape)  # the left column's
    ddx = jnp.broadcast_to(ddx[..., None], q.shape).reshape(hgt, wid)
    ddy = jnp.broadcast_to(ddy[:, None], q.shape).reshape(hgt, wid)
    return ddx, ddy


def decode(rep: dict, uv, dx, dy, step: float, *, filter: str = "trilinear"):
    """Sample and decode a representation: unit tangent-space normals (..., 3)."""
    name = rep["rep"]
    s = jaxnm.sample(rep["mips"], uv, dx, dy, filter=filter)
    if name in ("tangent8", "tangent16"):
        m = decode_normal_map(s)
    elif name in ("two_channel8", "bc5"):
        m = decode_normal_map(s, channels=2)
    elif name == "derivative8":
        return normal_from_gradient(s)
    elif name in ("height_coarse", "height_fine"):
        hx, hy = _quad_differences(s[..., 0], fine=name == "height_fine")
        shape = s.shape[:-1] + (3,)
        N = jnp.broadcast_to(jnp.float32([0.0, 0.0, 1.0]), shape)
        dpx = jnp.broadcast_to(jnp.float32([step, 0.0, 0.0]), shape)
        dpy = jnp.broadcast_to(jnp.float32([0.0, step, 0.0]), shape)
        return bump_normal(N, dpx, dpy, hx, hy)
    else:  # object8: the object-space normal, back in the plane's frame
        m = decode_normal_map(s)
        m = jnp.einsum("ji,...j->...i", jnp.asarray(ROTATION, m.dtype), m)
    return m / jnp.linalg.norm(m, axis=-1, keepdims=True)


# ---------------------------------------------------------------------- the sections


def magnification(reps: dict, size: int, *, pixels: int = 64, ppt: int = 8) -> dict:
    """Close up (``ppt`` pixels per texel): error against the analytic normal, the 99th
    percentile of neighbouring pixels' angle, and the crops (shading under a grazing light)
    for the figure."""
    uv, dx, dy, step = view(pixels, 1.0 / ppt, size)
    truth = truth_normal(uv[..., 0], uv[..., 1])
    light = np.array([0.8, 0.3, 0.52])
    light /= np.linalg.norm(light)
    rows, crops = {}, {"truth": np.clip(truth @ light, 0, 1)}
    jump_truth = angle(truth[:, 1:], truth[:, :-1])
    rows["truth"] = {"jump_p99": float(np.percentile(jump_truth, 99))}
    for name, rep in reps.items():
        n = np.asarray(decode(rep, uv, dx, dy, step), np.float64)
        rows[name] = {**_stats(angle(n, truth)),
                      "jump_p99": float(np.percentile(angle(n[:, 1:], n[:, :-1]), 99))}
        crops[name] = np.clip(n @ light, 0, 1)
    return {"pixels_per_texel": ppt, "rows": rows, "crops": crops}


def filtered_truth(size: int, uv, dx, dy, terms=BASE_TERMS) -> np.ndarray:
    """The exact normals at the texel centres, box-filtered into a mip chain and sampled by
    the same trilinear sampler, in float64, normalised: what any representation would give
    if it stored the normals exactly and the filter were the only loss."""
    u, v = texel_uv(size)
    with jax.enable_x64(True):
        mips = build_mipmaps(jnp.asarray(truth_normal(u, v, terms)))
        n = np.asarray(jaxnm.sample(mips, np.asarray(uv, np.float64), np.asarray(dx, np.float64),
                                    np.asarray(dy, np.float64), filter="trilinear"))
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def minification(reps: dict, size: int, distances, *, pixels: int = 64) -> dict:
    """Each distance (texels per pixel): error against `filtered_truth` (the representation's
    own loss) and against the footprint average of the analytic normals (the filter's too)."""
    out = {name: [] for name in reps}
    for k in distances:
        uv, dx, dy, step = view(pixels, k, size, shift=SHIFT)
        truth = filtered_truth(size, uv, dx, dy)
        ideal = footprint_truth(uv, step, max(4, int(np.ceil(2 * k))))
        for name, rep in reps.items():
            n = np.asarray(decode(rep, uv, dx, dy, step), np.float64)
            out[name].append({"texels_per_pixel": k, **_stats(angle(n, truth)),
                              "footprint_mean": float(angle(n, ideal).mean())})
    return out


def blend_methods(size: int) -> dict:
    """Every `blend_normal_maps` method at the texel centres (float32 decoded normals, as a
    shader holds them) against the float64 normal of the summed height fields; and the
    derivative maps added."""
    u, v = texel_uv(size)
    n1 = truth_normal(u, v, BASE_TERMS)
    n2 = truth_normal(u, v, DETAIL_TERMS)
    truth = truth_normal(u, v, BASE_TERMS + DETAIL_TERMS)
    rows = {}
    maps = {}
    for method in BLEND_METHODS:
        r = np.asarray(blend_normal_maps(n1.astype(np.float32), n2.astype(np.float32),
                                         method=method))
        err = angle(r, truth)
        rows[method] = _stats(err)
        maps[method] = err
    g = height(u, v, BASE_TERMS)[1] + height(u, v, DETAIL_TERMS)[1]
    err = angle(np.asarray(normal_from_gradient(g.astype(np.float32))), truth)
    rows["derivative maps added"] = _stats(err)
    return {"rows": rows, "error_maps": maps}


def blend_representations(size: int, *, pixels: int = 64) -> dict:
    """Each representation's own blend of base and detail, sampled one pixel per texel:
    normal maps by partial derivatives (the exact method), derivative maps and height maps by
    addition; against the summed fields' analytic normal at the pixel centres."""
    uv, dx, dy, step = view(pixels, 1.0, size)
    truth = truth_normal(uv[..., 0], uv[..., 1], BASE_TERMS + DETAIL_TERMS)
    rows = {}
    for name in REPRESENTATIONS:
        if name == "object8":
            rows[name] = None  # no tangent frame to lay a detail map in
            continue
        if name in ("derivative8", "height_coarse", "height_fine"):
            # one stored map of the summed field: what adding two maps gives, exactly
            # (up to each map's 8- or 16-bit codes, kept here at the sum's)
            rep = build(name, size, BASE_TERMS + DETAIL_TERMS)
            n = decode(rep, uv, dx, dy, step)
        else:
            a = decode(build(name, size, BASE_TERMS), uv, dx, dy, step)
            b = decode(build(name, size, DETAIL_TERMS), uv, dx, dy, step)
            n = blend_normal_maps(a, b, method="partial_derivative")
        rows[name] = _stats(angle(np.asarray(n, np.float64), truth))
    return rows


def encoders(size: int, extra_map: np.ndarray | None = None, *, repeats: int = 3) -> list:
    """The BC5 and DXT5nm encoders on the study's map (and ``extra_map``): code error (RMS,
    in 8-bit codes), the decoded normals' angle against the uncompressed 8-bit codes' and
    the encoding time; and whether texture2ddecoder and Pillow decode the blocks alike."""
    from jaxnm import storage

    u, v = texel_uv(size)
    maps = {"procedural": truth_normal(u, v).astype(np.float32)}
    if extra_map is not None:
        maps["your map"] = extra_map
    rows = []
    for label, n in maps.items():
        codes = np.round(np.asarray(quantize(encode_normal_map(n, channels=2), 8))
                         * 255).astype(np.uint8)
        ref = np.asarray(decode_normal_map(codes.astype(np.float32) / 255, channels=2))
        for fmt in storage.DDS_FORMATS:
            for enc in storage.ENCODERS:
                if enc == "angular" and fmt != "bc5":
                    continue
                t = time_call(lambda: storage.encode_blocks(codes, format=fmt, encoder=enc),
                              repeats=repeats)
                blocks = storage.encode_blocks(codes, format=fmt, encoder=enc)
                dec = storage.decode_blocks(blocks, codes.shape[:2], format=fmt)
                pil = storage.decode_blocks(blocks, codes.shape[:2], format=fmt,
                                            decoder="pillow")
                got = np.asarray(decode_normal_map(dec.astype(np.float32) / 255, channels=2))
                diff = dec.astype(np.float64) - codes
                rows.append({"map": label, "format": fmt, "encoder": enc,
                             "rms_codes": float(np.sqrt(np.mean(diff**2))),
                             "angle": _stats(angle(got, ref)),
                             "encode_ms": t.median_ms,
                             "decoders_agree": bool(np.array_equal(dec, pil))})
    return rows


#: The atlas's storages: label -> bits per texel. BC5 and DXT5nm store ``x, y`` (``z``
#: rebuilt), BC1 and BC7 all three channels (normalised after decoding).
ATLAS_STORAGES = {"RGB8": 24, "RG8, z rebuilt": 16, "RGB16": 48,
                  "BC5 quicktex": 8, "BC5 etcpak": 8, "BC5 Pillow": 8, "BC5 angular": 8,
                  "DXT5nm quicktex": 8, "DXT5nm etcpak": 8,
                  "BC1 quicktex": 4, "BC1 etcpak": 4, "BC7 etcpak": 8}


def _rebuilt(xy_codes, top: int = 255) -> np.ndarray:
    """Unit normals of (..., 2) codes, ``z`` rebuilt (float64)."""
    v = np.asarray(xy_codes, np.float64) / top * 2 - 1
    n = np.concatenate([v, np.sqrt(np.maximum(1 - (v**2).sum(-1), 0))[..., None]], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _normalised(rgb_codes, top: int = 255) -> np.ndarray:
    v = np.asarray(rgb_codes, np.float64) / top * 2 - 1
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _store(label: str, n: np.ndarray) -> tuple[np.ndarray, float | None]:
    """The unit normals ``n`` stored as ``label`` and decoded (float64), and the encoder's
    seconds (None for plain codes). Block data is decoded by texture2ddecoder."""
    import texture2ddecoder as t2d

    from jaxnm import storage

    h, w, _ = n.shape
    rgb8 = np.round((n + 1) / 2 * 255).astype(np.uint8)
    xy8 = np.ascontiguousarray(rgb8[..., :2])
    if label == "RGB8":
        return _normalised(rgb8), None
    if label == "RGB16":
        return _normalised(np.round((n + 1) / 2 * 65535), 65535), None
    if label == "RG8, z rebuilt":
        return _rebuilt(xy8), None
    kind, enc = label.split(" ", 1)
    if kind in ("BC5", "DXT5nm"):
        fmt = "bc5" if kind == "BC5" else "bc3nm"
        enc = enc.lower()
        t0 = time.perf_counter()
        blocks = storage.encode_blocks(xy8, format=fmt, encoder=enc)
        dt = time.perf_counter() - t0
        return _rebuilt(storage.decode_blocks(blocks, (h, w), format=fmt)), dt
    rgba = np.concatenate([rgb8, np.full((h, w, 1), 255, np.uint8)], -1).tobytes()
    t0 = time.perf_counter()
    if label == "BC1 quicktex":
        from quicktex import RawTexture
        from quicktex.s3tc.bc1 import BC1Encoder

        blocks = BC1Encoder(5).encode(RawTexture.frombytes(rgba, w, h)).tobytes()
    else:
        import etcpak

        blocks = bytes((etcpak.compress_bc1 if kind == "BC1" else etcpak.compress_bc7)(
            rgba, w, h))
    dt = time.perf_counter() - t0
    fn = t2d.decode_bc1 if kind == "BC1" else t2d.decode_bc7
    bgra = np.frombuffer(fn(blocks, w, h), np.uint8).reshape(h, w, 4)
    return _normalised(bgra[..., [2, 1, 0]]), dt


def _stats99(err) -> dict:
    err = np.asarray(err, np.float64).ravel()
    return {"mean": float(err.mean()), "p95": float(np.percentile(err, 95)),
            "p99": float(np.percentile(err, 99)), "max": float(err.max())}


def atlas_maps(*, quick: bool = False) -> dict:
    """The atlas's maps: the procedural one (unit normals of the height field, 512 texels, 128
    with ``quick``) and the real maps of `scripts.studies.real_maps` (``raw``: as stored,
    decoded, not unit length; ``unit``: renormalised)."""
    from scripts.studies import real_maps

    size = 128 if quick else 512
    u, v = texel_uv(size)
    proc = truth_normal(u, v)
    maps = {"procedural": {"raw": proc, "unit": proc, "source": None}}
    for m in real_maps.REAL_MAPS:
        raw, unit = real_maps.load(m)
        if quick:
            raw, unit = raw[:128, :128], unit[:128, :128]
        maps[m.name] = {"raw": raw, "unit": unit,
                        "source": {"package": m.package, "version": m.version,
                                   "path": m.path, "sha256": m.sha256, "title": m.title,
                                   "author": m.author, "license": m.license, "kind": m.kind,
                                   "url": m.source}}
    return maps


def unit_length(maps: dict) -> list:
    """How far each map's stored vectors are from unit length, and what rebuilding ``z``
    from the stored ``x, y`` without renormalising costs (against the renormalised map),
    beside renormalising first (both 8-bit two-channel codes)."""
    rows = []
    for name, m in maps.items():
        length = np.linalg.norm(m["raw"], axis=-1)
        raw_xy = np.round((np.clip(m["raw"][..., :2], -1, 1) + 1) / 2 * 255)
        unit_xy = np.round((m["unit"][..., :2] + 1) / 2 * 255)
        rows.append({"map": name, "length_mean": float(length.mean()),
                     "length_p1": float(np.percentile(length, 1)),
                     "length_p99": float(np.percentile(length, 99)),
                     "off_by_2pct": float(np.mean(np.abs(length - 1) > 0.02)),
                     "z_rebuilt_unnormalised": _stats99(angle(_rebuilt(raw_xy), m["unit"])),
                     "z_rebuilt_renormalised": _stats99(angle(_rebuilt(unit_xy), m["unit"]))})
    return rows


def atlas(maps: dict, *, warm: bool = True) -> list:
    """Every map stored every way of `ATLAS_STORAGES`: the angle (degrees) of the decoded
    normal to the map's float normal (renormalised), bits per texel and encode seconds.
    With ``warm`` the angular encoder is run once first at each size, so that its
    compilation is not timed."""
    from jaxnm import storage

    for shape in {m["unit"].shape[:2] for m in maps.values()} if warm else ():
        storage.encode_blocks(np.full(shape + (2,), 128, np.uint8), encoder="angular")
    rows = []
    for name, m in maps.items():
        for label, bits in ATLAS_STORAGES.items():
            dec, dt = _store(label, m["unit"])
            rows.append({"map": name, "storage": label, "bits_per_texel": bits,
                         **_stats99(angle(dec, m["unit"])),
                         "encode_s": dt, "size": list(m["unit"].shape[:2])})
    return rows


def angular_speed(size: int = 2048, repeats: int = 2) -> dict:
    """Seconds (wall and this process's CPU) of the angular encoder and quicktex on the
    procedural map at ``size`` texels, compiled first."""
    from jaxnm import storage

    u, v = texel_uv(size)
    xy8 = np.round((truth_normal(u, v)[..., :2] + 1) / 2 * 255).astype(np.uint8)
    out = {"size": size}
    t0, c0 = time.perf_counter(), time.process_time()
    storage.encode_blocks(xy8, encoder="angular")
    out["angular_first_call_s"] = time.perf_counter() - t0
    out["angular_first_call_cpu_s"] = time.process_time() - c0
    for enc in ("angular", "quicktex"):
        walls, cpus = [], []
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            storage.encode_blocks(xy8, encoder=enc)
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
        out[f"{enc}_s"], out[f"{enc}_cpu_s"] = min(walls), min(cpus)
    return out


def atlas_study(*, quick: bool = False) -> dict:
    """The atlas of storage error on the real maps and the procedural one, the maps' unit
    length, and the angular encoder's speed, with the machine's load before and after."""
    import datetime
    import os
    import subprocess

    load0 = os.getloadavg()
    try:  # the code that runs: read before the run, which takes minutes
        commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).parent, check=True).stdout.strip()
        modified = bool(subprocess.run(["git", "status", "--porcelain", "--", "jaxnm",
                                        "scripts"], capture_output=True, text=True,
                                       cwd=Path(__file__).parent, check=True).stdout.strip())
    except (OSError, subprocess.CalledProcessError):
        commit, modified = None, None
    t0 = time.perf_counter()
    maps = atlas_maps(quick=quick)
    res = {"maps": {k: {"size": list(m["unit"].shape[:2]), "source": m["source"]}
                    for k, m in maps.items()},
           "unit_length": unit_length(maps), "atlas": atlas(maps),
           "angular_speed": angular_speed(256 if quick else 2048, 1 if quick else 2),
           "held_out": held_out_fits(64, 32, fit_steps=10) if quick else held_out_fits()}
    res["metadata"] = {
        "date": datetime.date.today().isoformat(), "jaxnm": jaxnm.__version__,
        "jax": jax.__version__, "commit": commit, "modified": modified,
        "backend": jax.default_backend(),
        "machine": f"{platform.machine()}, {_cores()} cores", "python": platform.python_version(),
        "load_average_before": load0[0], "load_average_after": os.getloadavg()[0],
        "run_s": time.perf_counter() - t0,
        "command": "python -m scripts.studies.study_representations --atlas"
                   + (" --quick" if quick else "") + " --out DIR"}
    return res


#: The fitting problems of `stored_fits`: (render size, map size); the rivets of the built-in
#: map are 4 texels apart at 32 texels, 8 at 64 and 16 at 128.
STORED_PROBLEMS = ((128, 64), (256, 128))


def stored_fits(problems=STORED_PROBLEMS, *, fit_steps: int = 40) -> dict:
    """A fit through BC5 (and 8-bit codes) against a float map compressed afterwards, on the
    built-in fitting problem (the torus and its rivet map, 2 views x 6 lights, noise-free
    targets) at each (render size, map size) of ``problems``: the shading loss and the mean
    angular error of each map *as stored* (the stored bytes decoded by texture2ddecoder).
    Two float maps start it: the exact map (what a perfect float fit would find) and a float
    fit of ``fit_steps`` steps. The residual images are the first problem's (view 0, mean
    over its lights)."""
    from jaxnm import storage as st
    from jaxnm.fit import FitOptions, fit_normal_map, prepare, render_with_map
    from jaxnm.fit.stored import fit_stored_map
    from jaxnm.procedural import default_problem

    rows, fits, images = [], [], {}
    for render_size, map_size in problems:
        problem, gt, _ = default_problem(render_size=render_size, map_size=map_size,
                                         n_lights=6, views=2)
        prep = prepare(problem)
        t0 = time.perf_counter()
        fit = fit_normal_map(problem, FitOptions(max_steps=fit_steps), prepared=prep,
                             progress=False)
        fits.append({"render_size": render_size, "map_size": map_size, "steps": fit_steps,
                     "stopped": fit.stopped, "loss": fit.best_loss,
                     "seconds": time.perf_counter() - t0})
        for start_name, start in (("exact map", gt), ("float fit", fit)):
            for storage in ("bc5", "rgb8"):
                sf = fit_stored_map(problem, storage=storage, start=start, prepared=prep,
                                    ground_truth=gt)
                rows.append({"render_size": render_size, "map_size": map_size,
                             "start": start_name, "storage": storage,
                             "loss_float": sf.float_loss,
                             "loss_compressed_afterwards": sf.start_loss,
                             "loss_stored": sf.loss, "error_float": sf.errors["float"],
                             "error_compressed_afterwards": sf.errors["start_stored"],
                             "error_stored": sf.errors["stored"], "seconds": sf.seconds,
                             "steps": len([h for h in sf.history if h["phase"] != "reindex"])})
                if start_name == "exact map" and storage == "bc5" and not images:
                    codes = np.round(np.asarray(encode_normal_map(gt, channels=2)) * 255)
                    after = st.decode_blocks(st.encode_blocks(codes.astype(np.uint8)),
                                             gt.shape[:2]).astype(np.float32) / 255
                    target = prep.target_images(0)
                    for name, texels in (("compressed afterwards", after),
                                         ("fitted through BC5", sf.texels)):
                        n = np.asarray(decode_normal_map(texels, channels=2))
                        img = render_with_map(prep, n)[0]
                        images[name] = np.abs(img - target).mean((0, -1))
    return {"views": 2, "lights": 6, "float_fits": fits, "rows": rows, "images": images}


def held_out_fits(render_size: int = 128, map_size: int = 64, *, fit_steps: int = 40) -> dict:
    """The fit through BC5 under views and lights it did not use. The built-in problem
    (2 views x 6 lights) is fitted as a float map, then stored as BC5 four ways: the float
    map compressed afterwards by quicktex or by the angular encoder, and fitted through the
    blocks (`jaxnm.fit.fit_stored_map`) from quicktex's or the angular encoder's blocks.
    Each map as stored is scored in PSNR (dB, the targets' peak, over covered pixels) under
    the fitted targets, under 6 other lights in the same 2 views, and under the third view
    with those lights (``default_problem(views=3, seed=1)``), and by its angle to the true
    map over the texels the fit saw."""
    from jaxnm import storage as st
    from jaxnm.fit import FitOptions, fit_normal_map, prepare, render_with_map, seen_texels
    from jaxnm.fit.stored import fit_stored_map
    from jaxnm.procedural import default_problem

    problem, gt, _ = default_problem(render_size=render_size, map_size=map_size, n_lights=6,
                                     views=2)
    other, _, _ = default_problem(render_size=render_size, map_size=map_size, n_lights=6,
                                  views=3, seed=1)
    prep, prep_other = prepare(problem), prepare(other)
    seen = seen_texels(prep, (map_size, map_size))
    t0 = time.perf_counter()
    fit = fit_normal_map(problem, FitOptions(max_steps=fit_steps), prepared=prep,
                         progress=False)
    float_s = time.perf_counter() - t0
    codes = np.round(np.asarray(encode_normal_map(fit.normals, channels=2)) * 255)
    codes = codes.astype(np.uint8)
    maps, seconds = {"float fit, unstored": np.asarray(fit.normals, np.float64)}, {}
    for enc in ("quicktex", "angular"):
        blocks = st.encode_blocks(codes, encoder=enc)
        maps[f"{enc} afterwards"] = _rebuilt(st.decode_blocks(blocks, codes.shape[:2]))
    for enc in ("quicktex", "angular"):
        t0 = time.perf_counter()
        sf = fit_stored_map(problem, storage="bc5", start=fit, encoder=enc, prepared=prep)
        seconds[f"fitted through BC5 from {enc}"] = time.perf_counter() - t0
        maps[f"fitted through BC5 from {enc}"] = _rebuilt(
            np.round(np.asarray(sf.texels) * 255))

    def psnr(p, views, n):
        se, count, peak = 0.0, 0, 0.0
        imgs = render_with_map(p, jnp.asarray(n, jnp.float32))
        for v in views:
            target = p.target_images(v)
            for t in range(target.shape[0]):
                mask = p.target_mask(v, t)
                d = (imgs[v][t] - target[t])[mask]
                se, count = se + float((d.astype(np.float64) ** 2).sum()), count + d.size
                peak = max(peak, float(target[t].max()))
        return float(10 * np.log10(peak**2 / (se / count)))

    rows = []
    for name, n in maps.items():
        err = angle(n, gt)[seen]
        rows.append({"map": name, "psnr_fitted": psnr(prep, (0, 1), n),
                     "psnr_other_lights": psnr(prep_other, (0, 1), n),
                     "psnr_other_view": psnr(prep_other, (2,), n),
                     "angle_mean": float(err.mean()),
                     "angle_p99": float(np.percentile(err, 99)),
                     "seconds": seconds.get(name)})
    return {"render_size": render_size, "map_size": map_size, "fit_steps": fit_steps,
            "float_fit_s": float_s, "seen_texels": int(seen.sum()), "rows": rows}


def _lobe_of(n, h):
    return FL.blinn_phong_lobe(n, jnp.broadcast_to(jnp.asarray(h, n.dtype), n.shape),
                               SHININESS)


def specular(size: int, distances, *, pixels: int = 48, ss_min: int = 4) -> dict:
    """Specular aliasing: Blinn-Phong lobes of the (float) map at each distance, for each
    filtering choice, against the supersampled reference."""
    u, v = texel_uv(size)
    n0 = truth_normal(u, v).astype(np.float32)
    chains = {"renormalized": FL.normal_mipmaps(n0, mode="renormalize"),
              "shortened": FL.normal_mipmaps(n0, mode="shortened")}
    lean = build_mipmaps(FL.lean_moments(n0))
    out = {c: [] for c in FILTER_CHOICES}
    out["reference"] = []
    for k in distances:
        uv, dx, dy, step = view(pixels, k, size, shift=SHIFT)
        ref = reference_specular(chains["shortened"][0], uv, step, max(ss_min,
                                                                       int(np.ceil(2 * k))))
        h = jnp.broadcast_to(jnp.asarray(HALF, jnp.float32), uv.shape[:-1] + (3,))
        vals = {}
        s = jaxnm.sample(chains["shortened"][0], uv, dx, dy, filter="bilinear")
        vals["no_mips"] = _lobe_of(s / jnp.linalg.norm(s, axis=-1, keepdims=True), HALF)
        for c in ("renormalized", "shortened"):
            s = jaxnm.sample(chains[c], uv, dx, dy, filter="trilinear")
            vals[c] = _lobe_of(s / jnp.linalg.norm(s, axis=-1, keepdims=True), HALF)
        s = jaxnm.sample(chains["shortened"], uv, dx, dy, filter="trilinear")
        vals["toksvig"] = FL.toksvig_specular(s, h, SHININESS)
        m = jaxnm.sample(lean, uv, dx, dy, filter="trilinear")
        vals["lean"] = FL.lean_specular(m, h, SHININESS)
        ref_mean = float(ref.mean())
        out["reference"].append({"texels_per_pixel": k, "mean": ref_mean})
        for c in FILTER_CHOICES:
            x = np.asarray(vals[c], np.float64)
            out[c].append({"texels_per_pixel": k,
                           "rms": float(np.sqrt(np.mean((x - ref) ** 2))),
                           "mean_bias": float((x.mean() - ref_mean) / ref_mean)})
        if k == distances[len(distances) // 2]:
            out["images"] = {"texels_per_pixel": k, "reference": ref,
                             **{c: np.asarray(vals[c]) for c in FILTER_CHOICES}}
    return out


def reference_specular(level0, uv, step: float, ss: int) -> np.ndarray:
    """The supersampled reference: each pixel's mean lobe over ``ss`` x ``ss`` stratified
    bilinear samples of level 0 within its footprint."""
    o = ((np.arange(ss) + 0.5) / ss - 0.5) * step
    acc = np.zeros(uv.shape[:-1])
    level0 = jnp.asarray(level0)
    for dv in o:  # one row of sub-samples at a time
        p = uv[..., None, :] + np.stack([o, np.full(ss, dv)], -1).astype(np.float32)
        s = jaxnm.sample(level0, p, filter="bilinear")
        lobe = _lobe_of(s / jnp.linalg.norm(s, axis=-1, keepdims=True), HALF)
        acc += np.asarray(lobe, np.float64).sum(-1)
    return acc / ss**2


def speeds(reps: dict, size: int, *, pixels: int = 256, repeats: int = 10) -> dict:
    """Median ms of sampling and decoding a ``pixels``^2 view (two texels a pixel) with
    each representation, compiled (`jax.jit`), on this machine's default JAX device; the
    representations take turns in blocks (`side_by_side`), so that a slow spell of the
    machine falls on all of them alike. ``tangent8`` and ``tangent16`` run the same program
    (float textures of the same shape): their difference is the measurement's noise."""
    uv, dx, dy, step = view(pixels, 2.0, size, shift=SHIFT)
    args = (jnp.asarray(uv), jnp.asarray(dx), jnp.asarray(dy))
    calls = {}
    for name, rep in reps.items():
        fn = jax.jit(lambda mips, uv, dx, dy, rep=rep: decode({**rep, "mips": mips}, uv, dx,
                                                              dy, step))
        calls[name] = (lambda fn=fn, mips=rep["mips"]: fn(mips, *args))
    # three rounds, each representation's least disturbed median kept (a shared machine's
    # other work slows a round's calls unevenly)
    rounds = [side_by_side(calls, repeats, block=5, warm=3, warm_s=0.1, seed=r,
                           first_calls=r == 0)[1] for r in range(3)]
    return {name: min(r[name] for r in rounds) for name in calls}


# ---------------------------------------------------------------------- figures


def _figures(res: dict, out: Path) -> list[str]:
    try:
        from matplotlib.figure import Figure
    except ImportError:
        print("matplotlib missing: no figures (pip install '.[notebook]')")
        return []
    caption = res["meta"]["caption"]
    written = []

    def save(fig, name):
        fig.text(0.5, 0.005, caption, ha="center", va="bottom", fontsize=6, color="0.35")
        fig.savefig(out / name)
        written.append(name)

    mag = res["magnification"]
    names = ["truth", "tangent8", "bc5", "derivative8", "height_fine", "height_coarse"]
    fig = Figure(figsize=(2.0 * len(names), 2.5), dpi=80)
    for i, name in enumerate(names):
        ax = fig.add_subplot(1, len(names), i + 1)
        ax.imshow(mag["crops"][name], cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        jump = mag["rows"][name]["jump_p99"]
        ax.set_title(f"{name}\njump p99 {jump:.2f}°", fontsize=8)
        ax.set_axis_off()
    fig.suptitle(f"close-up, {mag['pixels_per_texel']} pixels per texel, grazing light",
                 fontsize=9)
    fig.subplots_adjust(bottom=0.08, top=0.78, wspace=0.05, left=0.01, right=0.99)
    save(fig, "fig_magnification.png")

    fig = Figure(figsize=(6.4, 3.6), dpi=80)
    ax = fig.add_subplot()
    for name, rows in res["minification"].items():
        ax.plot([r["texels_per_pixel"] for r in rows], [r["mean"] for r in rows], "o-",
                label=name, ms=3)
    ax.set(xscale="log", yscale="log", xlabel="texels per pixel (distance)",
           ylabel="mean error (deg)",
           title="minification: against the exact normals, filtered alike")
    ax.legend(fontsize=7, ncol=2)
    fig.subplots_adjust(bottom=0.2)
    save(fig, "fig_minification.png")

    bl = res["blend"]
    methods = list(BLEND_METHODS)
    fig = Figure(figsize=(2.0 * len(methods), 2.6), dpi=70)
    vmax = 5.0
    for i, m in enumerate(methods):
        ax = fig.add_subplot(1, len(methods), i + 1)
        ax.imshow(bl["error_maps"][m][:96, :96], vmin=0, vmax=vmax, cmap="magma",
                  interpolation="nearest")
        ax.set_title(f"{m}\nmean {bl['rows'][m]['mean']:.3g}°", fontsize=8)
        ax.set_axis_off()
    fig.suptitle(f"blend error against the summed height fields, 96x96 texels (0 to {vmax:g}°"
                 " and above)",
                 fontsize=9)
    fig.subplots_adjust(bottom=0.08, top=0.76, wspace=0.05, left=0.01, right=0.99)
    save(fig, "fig_blend.png")

    enc = [r for r in res["encoders"] if r["map"] == "procedural"]
    fig = Figure(figsize=(6.4, 3.2), dpi=80)
    ax = fig.add_subplot()
    labels = [f"{r['format']}\n{r['encoder']}" for r in enc]
    ax.bar(range(len(enc)), [r["angle"]["mean"] for r in enc], color="tab:blue")
    ax.set_xticks(range(len(enc)), labels, fontsize=7)
    ax.set(ylabel="mean angle (deg)", title="block compression against the 8-bit codes")
    fig.subplots_adjust(bottom=0.25)
    save(fig, "fig_storage.png")

    sp = res["specular"]
    imgs = sp["images"]
    fig = Figure(figsize=(10, 3.4), dpi=80)
    ax = fig.add_subplot(1, 2, 1)
    for c in FILTER_CHOICES:
        ax.plot([r["texels_per_pixel"] for r in sp[c]], [r["rms"] for r in sp[c]], "o-",
                label=c, ms=3)
    ax.set(xscale="log", xlabel="texels per pixel (distance)", ylabel="RMS vs reference",
           title=f"specular aliasing (Blinn-Phong, s = {SHININESS:g})")
    ax.legend(fontsize=7)
    shown = ("reference", "no_mips", "renormalized", "toksvig", "lean")
    vmax = float(np.percentile(imgs["reference"], 99.5)) or 1.0
    for i, c in enumerate(shown):
        a = fig.add_subplot(2, 6, 4 + i + (3 if i > 2 else 0))
        a.imshow(imgs[c], cmap="gray", vmin=0, vmax=vmax, interpolation="nearest")
        a.set_title(c, fontsize=7)
        a.set_axis_off()
    fig.text(0.75, 0.93, f"{imgs['texels_per_pixel']:g} texels per pixel", ha="center",
             fontsize=8)
    fig.subplots_adjust(bottom=0.2, wspace=0.1)
    save(fig, "fig_specular.png")

    st = res.get("stored_fit")
    if st:
        fig = Figure(figsize=(10, 3.4), dpi=80)
        ax = fig.add_subplot(1, 3, 1)
        rows = [r for r in st["rows"] if r["storage"] == "bc5"]
        kinds = (("loss_float", "float (unstored)"),
                 ("loss_compressed_afterwards", "quicktex afterwards"),
                 ("loss_stored", "fitted through BC5"))
        x = np.arange(len(rows))
        for i, (key, label) in enumerate(kinds):
            ax.bar(x + (i - 1) * 0.27, [max(r[key], 1e-12) for r in rows], 0.27, label=label)
        ax.set_xticks(x, [f"{r['start']}\n{r['map_size']}²" for r in rows], fontsize=7)
        ax.set(yscale="log", ylabel="shading loss as stored", title="BC5: loss as stored")
        ax.legend(fontsize=6, loc="center")
        imgs = st["images"]
        vmax = float(max(np.percentile(v, 99.5) for v in imgs.values())) or 1.0
        for i, (name, img) in enumerate(imgs.items()):
            a = fig.add_subplot(1, 3, 2 + i)
            a.imshow(img, cmap="magma", vmin=0, vmax=vmax, interpolation="nearest")
            a.set_title(f"|render - target|, {name}\n({st['rows'][0]['map_size']}² map, exact "
                        "start)", fontsize=8)
            a.set_axis_off()
        fig.subplots_adjust(bottom=0.2, wspace=0.15)
        save(fig, "fig_stored.png")
    return written


# ---------------------------------------------------------------------- main


def _load_png_normals(path: str) -> np.ndarray:
    raw, _ = jio.load_texture(path, channels=3)
    n = np.asarray(decode_normal_map(raw), np.float64)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    h, w = n.shape[:2]
    return n[:h - h % 4, :w - w % 4].astype(np.float32)


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()
                if k not in ("crops", "error_maps", "images")}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


def run(*, quick: bool = False, extra_map: np.ndarray | None = None) -> dict:
    """The whole study; the figures' arrays are kept in the result (not in the JSON)."""
    size = 256
    distances = (1, 2, 4, 8, 16) if quick else (1, 1.5, 2, 3, 4, 6, 8, 12, 16)
    spec_distances = (1, 2, 4, 8, 16) if quick else (1, 1.5, 2, 3, 4, 6, 8, 12, 16, 24, 32)
    t0 = time.perf_counter()
    reps = {name: build(name, size) for name in REPRESENTATIONS}
    res = {
        "magnification": magnification(reps, size, pixels=48 if quick else 64),
        "minification": minification(reps, size, distances, pixels=32 if quick else 64),
        "blend": blend_methods(size),
        "blend_representations": blend_representations(size, pixels=32 if quick else 64),
        "storage_bytes_per_texel": BYTES_PER_TEXEL,
        "encoders": encoders(size, extra_map, repeats=3 if quick else 10),
        "specular": specular(size, spec_distances, pixels=24 if quick else 48),
        "speed_ms": speeds(reps, size, pixels=128 if quick else 256,
                           repeats=5 if quick else 20),
        # (--quick leaves the fits out: tests/test_stored_fit.py runs a small one)
        "stored_fit": None if quick else stored_fits(),
    }
    res["meta"] = {"size": size, "quick": quick, "seconds": time.perf_counter() - t0,
                   "jaxnm": jaxnm.__version__, "jax": jax.__version__,
                   "device": jax.devices()[0].device_kind,
                   "machine": f"{platform.machine()}, {_cores()} cores",
                   "command": "python -m scripts.studies.study_representations"
                              + (" --quick" if quick else "")}
    res["meta"]["caption"] = (f"{res['meta']['command']} · jaxnm {jaxnm.__version__}, JAX "
                              f"{jax.__version__}, {res['meta']['machine']}")
    return res


def _cores() -> int:
    import os

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="representations_out")
    ap.add_argument("--quick", action="store_true", help="a 128-texel map, smaller views")
    ap.add_argument("--map", help="a tangent-space normal map (8-bit PNG) for the encoders")
    ap.add_argument("--atlas", action="store_true",
                    help="only the atlas of storage error on real maps (fetched from Debian "
                         "packages by scripts.studies.real_maps): representations_atlas.json")
    args = ap.parse_args(argv)
    output("--out", args.out, folder=True)  # before the work
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.atlas:
        res = atlas_study(quick=args.quick)
        (out / "representations_atlas.json").write_text(json.dumps(res, indent=1) + "\n")
        print(json.dumps({k: res[k] for k in ("unit_length", "angular_speed", "metadata")},
                         indent=1))
        return res
    extra = _load_png_normals(args.map) if args.map else None
    res = run(quick=args.quick, extra_map=extra)
    figs = _figures(res, out)
    res["meta"]["seconds_with_figures"] = res["meta"]["seconds"]
    (out / "representations.json").write_text(json.dumps(_jsonable(res), indent=1) + "\n")
    print(json.dumps(_jsonable({k: res[k] for k in ("magnification", "blend", "speed_ms",
                                                     "meta")}), indent=1))
    print("figures:", ", ".join(figs))
    return res


if __name__ == "__main__":
    sys.exit(run_script(main))
