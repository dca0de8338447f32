"""Regenerate the tiny glTF test assets of tests/test_io.py (run from anywhere).

Written with numpy, json and struct only (not trimesh, not jaxnm), so the tests
compare jaxnm's loader with data known independently. glTF puts the uv origin at
the TOP-left of the image; the raw TEXCOORD_0 values below are in that convention.

- ``tri_uv.gltf`` + ``tri_uv.bin``: one triangle with TEXCOORD_0, NORMAL and a
  material (with a baseColorTexture whose image file is deliberately absent).
- ``two_nodes.glb``: one triangle mesh (TEXCOORD_0, no NORMAL, no material)
  instanced by two nodes: a translation, and a mirroring matrix.
"""

import json
import struct
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

POSITIONS = np.array([[0, 0, 0], [2, 0, 0], [0, 1, 0]], np.float32)
# glTF (top-left origin) texture coordinates; binary fractions, so 1 - v is exact
UV_GLTF = np.array([[0.25, 0.125], [0.75, 0.125], [0.25, 0.625]], np.float32)
NORMALS = np.array([[0, 0, 1], [0, 0.6, 0.8], [0.6, 0, 0.8]], np.float32)
INDICES = np.array([0, 1, 2], np.uint16)
# node 1 of two_nodes.glb: x mirrored, y scaled by 2, translated by +5 in z
NODE1_MATRIX = np.array([[-1, 0, 0, 0], [0, 2, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]], np.float32)


def _buffer(arrays):
    """(bytes, bufferViews) of arrays laid end to end, each 4-byte aligned."""
    blob, views = b"", []
    for a in arrays:
        data = a.tobytes()
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
        blob += data + b"\0" * (-len(data) % 4)
    return blob, views


def _triangle_gltf(*, with_normals, with_material):
    arrays = [POSITIONS, UV_GLTF, INDICES] + ([NORMALS] if with_normals else [])
    blob, views = _buffer(arrays)
    accessors = [
        {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
         "min": POSITIONS.min(0).tolist(), "max": POSITIONS.max(0).tolist()},
        {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC2"},
        {"bufferView": 2, "componentType": 5123, "count": 3, "type": "SCALAR"},
    ]
    attributes = {"POSITION": 0, "TEXCOORD_0": 1}
    if with_normals:
        accessors.append({"bufferView": 3, "componentType": 5126, "count": 3, "type": "VEC3"})
        attributes["NORMAL"] = 3
    primitive = {"attributes": attributes, "indices": 2}
    tree = {"asset": {"version": "2.0"}, "meshes": [{"primitives": [primitive]}],
            "accessors": accessors, "bufferViews": views,
            "buffers": [{"byteLength": len(blob)}]}
    if with_material:
        primitive["material"] = 0
        tree["materials"] = [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]
        tree["textures"] = [{"source": 0}]
        tree["images"] = [{"uri": "tri_uv_missing_texture.png"}]
    return tree, blob


def write_tri_uv():
    tree, blob = _triangle_gltf(with_normals=True, with_material=True)
    tree["buffers"][0]["uri"] = "tri_uv.bin"
    tree["nodes"] = [{"mesh": 0}]
    tree["scenes"] = [{"nodes": [0]}]
    tree["scene"] = 0
    (HERE / "tri_uv.bin").write_bytes(blob)
    (HERE / "tri_uv.gltf").write_text(json.dumps(tree, indent=1) + "\n")


def write_two_nodes():
    tree, blob = _triangle_gltf(with_normals=False, with_material=False)
    tree["nodes"] = [
        {"mesh": 0, "translation": [10.0, 0.0, 0.0]},
        {"mesh": 0, "matrix": NODE1_MATRIX.T.reshape(-1).tolist()},  # column-major
    ]
    tree["scenes"] = [{"nodes": [0, 1]}]
    tree["scene"] = 0
    js = json.dumps(tree).encode()
    js += b" " * (-len(js) % 4)
    chunks = struct.pack("<I4s", len(js), b"JSON") + js
    chunks += struct.pack("<I4s", len(blob), b"BIN\0") + blob
    (HERE / "two_nodes.glb").write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(chunks))
                                         + chunks)


if __name__ == "__main__":
    write_tri_uv()
    write_two_nodes()
    for p in sorted(HERE.iterdir()):
        print(f"{p.name:24s} {p.stat().st_size:6d} bytes")
