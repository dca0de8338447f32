"""Real normal maps for the representations study, fetched from Debian's game-data packages.

    python -m scripts.studies.real_maps [--cache DIR]

Each map is one file of a Debian package at a pinned version: the package is downloaded with
``apt-get download PACKAGE=VERSION`` and the file extracted (``dpkg-deb --fsys-tarfile``)
into ``CACHE/PACKAGE_VERSION/`` (default ``~/.cache/jaxnm/normal-maps``, outside the
repository), with the package's ``copyright`` file beside it; its SHA-256 is checked against
the pinned one. Nothing here is committed to the repository.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import os
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

from scripts._cli import run_script


@dataclasses.dataclass(frozen=True)
class RealMap:
    name: str  #: the study's label
    package: str
    version: str
    path: str  #: inside the package
    sha256: str
    title: str
    author: str
    license: str
    kind: str  #: "scanned" or "artist"
    source: str = ""  #: where the author published it, if the package names it


REAL_MAPS = (
    RealMap("ground (ambientCG)", "supertuxkart-data", "1.4+dfsg-2",
            "usr/share/games/supertuxkart/data/tracks/cave/Ground010_1K_Normal.png",
            "cae746ea9722b9a4b02463a71d5dbe608ce90403b3878b0ba1a6c390f0ebed8f",
            "Ground010, 1K", "ambientCG", "CC0 1.0", "scanned",
            "https://ambientcg.com/view?id=Ground010"),
    RealMap("cobblestone (SuperTuxKart)", "supertuxkart-data", "1.4+dfsg-2",
            "usr/share/games/supertuxkart/data/textures/"
            "stktex_generic_cobbleStoneA_Normal.png",
            "dc4250a3dfb9ae972f27e124313733507d373bd31a48005302db69853fd94f78",
            "stktex_generic_cobbleStoneA_Normal", "Jean-Manuel Clémençon (SuperTuxKart)",
            "CC-BY-SA 3.0", "artist"),
    RealMap("red rock (Red Eclipse)", "redeclipse-data", "1.6.0-1",
            "usr/share/games/redeclipse/data/jojo/redrock04_n.png",
            "87050ee19642e670a4f9f1d8da32ec94f10816759539d5c264bed3be8fbe2cd8",
            "redrock04_n", "Red Eclipse Team (textures by jojo)", "CC-BY-SA 3.0 or later",
            "artist"),
    RealMap("metal panels (Red Eclipse)", "redeclipse-data", "1.6.0-1",
            "usr/share/games/redeclipse/data/mikeplus64/metalpanels_n.png",
            "9368182aea3667dba86e23ad80938f4ebfb8514cb443e1c51ecc25abee1459e6",
            "metalpanels_n", "Red Eclipse Team (textures by mikeplus64)",
            "CC-BY-SA 3.0 or later", "artist"),
)


def default_cache() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "jaxnm" / \
        "normal-maps"


def _extract(deb: Path, members: list[str], into: Path) -> None:
    """Extract ``members`` (paths without the leading ``./``) of a .deb's data into ``into``."""
    proc = subprocess.Popen(["dpkg-deb", "--fsys-tarfile", str(deb)], stdout=subprocess.PIPE)
    want = set(members)
    with tarfile.open(fileobj=proc.stdout, mode="r|*") as tar:
        for m in tar:
            name = m.name.removeprefix("./")
            if name in want and m.isfile():
                out = into / name
                out.parent.mkdir(parents=True, exist_ok=True)
                out.write_bytes(tar.extractfile(m).read())
                want.discard(name)
    proc.stdout.close()
    proc.wait()
    if want:
        raise FileNotFoundError(f"{deb.name}: no {', '.join(sorted(want))}")


def fetch(m: RealMap, cache: Path | None = None) -> Path:
    """The map's file in the cache, downloaded and extracted the first time."""
    folder = (cache or default_cache()) / f"{m.package}_{m.version}"
    out = folder / m.path
    if not out.exists():
        folder.mkdir(parents=True, exist_ok=True)
        wanted = [x.path for x in REAL_MAPS if x.package == m.package
                  and x.version == m.version] + [f"usr/share/doc/{m.package}/copyright"]
        with tempfile.TemporaryDirectory() as tmp:
            subprocess.run(["apt-get", "download", f"{m.package}={m.version}"], cwd=tmp,
                           check=True, capture_output=True)
            (deb,) = Path(tmp).glob("*.deb")
            _extract(deb, wanted, folder)
    digest = hashlib.sha256(out.read_bytes()).hexdigest()
    if m.sha256 and digest != m.sha256:
        raise ValueError(f"{out}: SHA-256 {digest}, expected {m.sha256}")
    return out


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def load(m: RealMap, cache: Path | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(raw, unit)``: the map's 8-bit RGB decoded to [-1, 1] as stored (float64, not unit
    length), and renormalised (``z`` clamped to >= 0 first); cropped to a multiple of 4."""
    from PIL import Image

    with Image.open(fetch(m, cache)) as im:
        rgb = np.asarray(im.convert("RGB"), np.float64)
    h, w = rgb.shape[0] // 4 * 4, rgb.shape[1] // 4 * 4
    raw = rgb[:h, :w] / 255 * 2 - 1
    unit = raw.copy()
    unit[..., 2] = np.maximum(unit[..., 2], 0)
    unit /= np.maximum(np.linalg.norm(unit, axis=-1, keepdims=True), 1e-12)
    return raw, unit


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=None)
    args = ap.parse_args(argv)
    for m in REAL_MAPS:
        p = fetch(m, args.cache)
        print(f"{m.name}: {p} sha256 {sha256(p)}")


if __name__ == "__main__":
    sys.exit(run_script(main))
