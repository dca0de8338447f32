"""jaxnm.fit.stored: a fit through BC5 blocks and 8-bit codes. The blocks it writes decode,
with texture2ddecoder, to the texels its model fitted (rounding, truncation and swapped
endpoints included); its loss as stored is lower than the float map compressed by quicktex
afterwards, measured on the files each writes."""

import numpy as np
import pytest

pytest.importorskip("quicktex")
pytest.importorskip("texture2ddecoder")

import jax.numpy as jnp  # noqa: E402
import texture2ddecoder  # noqa: E402

from jaxnm import storage as S  # noqa: E402
from jaxnm.fit import ModelArgs, prepare  # noqa: E402
from jaxnm.fit import stored as ST  # noqa: E402
from jaxnm.procedural import default_problem  # noqa: E402


def test_rounded_blocks_decode_as_the_decoder_library_reads_their_bytes():
    """Real endpoints held in either mode, rounded (the straight-through forward), with the
    decoder's truncation: the texels equal texture2ddecoder's decode of the bytes written for
    them (swapped endpoints remapped, met endpoints collapsed)."""
    rng = np.random.default_rng(0)
    bh = bw = 8
    e = rng.uniform(0, 255, (bh, bw, 2, 2)).astype(np.float32)
    e[0, 0, 0] = [100.2, 99.9]  # rounds to equal endpoints in the eight-value mode
    e[0, 1, 0] = [50.0, 50.3]
    idx = rng.integers(0, 8, (bh, bw, 2, 16)).astype(np.uint8)
    eight = rng.random((bh, bw, 2)) < 0.5  # modes held fixed whatever the endpoints' order
    eight[0, :2, 0] = True
    lay = ST._Layout("bc5", (4 * bh, 4 * bw), "up", "bottom_left")
    fixed = (jnp.asarray(idx), jnp.asarray(eight))
    ours = np.asarray(ST._raw(jnp.asarray(e), fixed, lay, np.bool_(True))) * 255
    q = np.round(e).astype(np.uint8)
    e2, i2, eight2 = ST._canonical(q, idx, eight)
    assert ((q[..., 0] > q[..., 1]) != eight).any()  # some blocks did need a swap
    np.testing.assert_array_equal(eight2, e2[..., 0] > e2[..., 1])
    blocks = S.pack_bc4_blocks(e2.reshape(-1, 2), i2.reshape(-1, 16))
    lib = np.frombuffer(texture2ddecoder.decode_bc5(blocks, 4 * bw, 4 * bh), np.uint8)
    lib = lib.reshape(4 * bh, 4 * bw, 4)[..., [2, 1]]  # BGRA: red, green
    np.testing.assert_allclose(ours, lib, atol=1e-3)
    # unrounded, the texels are affine in the endpoints: a central difference is exact
    # and equals the palette's weight, ((8 - i) / 7, (i - 1) / 7) for i >= 2 in eight-value
    # mode and ((6 - i) / 5, (i - 1) / 5) for 2 <= i <= 5 in six-value mode
    d = np.zeros_like(e)
    d[..., 0] = 1.0
    lo, hi = (np.asarray(ST._raw(jnp.asarray(e + s * d), fixed, lay, np.bool_(False)),
                         np.float64) * 255 for s in (-0.5, 0.5))
    fd = ST._blockwise(hi - lo)  # (block row, block column, channel, texel)
    expect = np.where(eight[..., None], (8.0 - idx) / 7, np.where(idx <= 5, (6.0 - idx) / 5, 0))
    expect = np.where(idx == 0, 1.0, np.where(idx == 1, 0.0, expect))
    assert fd.shape == expect.shape
    np.testing.assert_allclose(fd, expect, atol=2e-3)


@pytest.fixture(scope="module")
def problem():
    problem, gt, _ = default_problem(render_size=48, map_size=32, n_lights=4, views=1)
    return problem, gt, prepare(problem)


def test_a_fit_through_bc5_beats_compressing_the_float_map_afterwards(problem, tmp_path):
    """Conclusion: starting from the exact map (a float fit's ideal), quicktex's BC5 blocks
    lose much of the shading; endpoints fitted to the shading through the blocks lose less.
    Both measured on the DDS files each way writes, decoded by texture2ddecoder."""
    prob, gt, prep = problem
    sf = ST.fit_stored_map(prob, storage="bc5", start=gt, prepared=prep, rounds=2, steps=4,
                           cg_steps=10, ground_truth=gt)
    args = ModelArgs.create(prep, reduce=True)
    path = tmp_path / "stored.dds"
    sf.save(path)
    m = S.load_dds_normal_map(path)
    np.testing.assert_array_equal(m.texels, sf.texels)
    assert sf.map_options.channels == 2
    after = S.save_dds_normal_map(tmp_path / "after.dds", gt, format="bc5", encoder="quicktex")
    assert after.shape == (32, 32, 2)
    baseline = ST.stored_loss(S.load_dds_normal_map(tmp_path / "after.dds").texels,
                              sf.map_options, args)
    ours = ST.stored_loss(m.texels, sf.map_options, args)
    np.testing.assert_allclose([ours, baseline], [sf.loss, sf.start_loss], rtol=1e-5)
    assert sf.float_loss < 1e-3 * baseline  # the exact map fits its noise-free targets
    assert ours < 0.8 * baseline, (ours, baseline)
    assert set(sf.errors) == {"float", "start_stored", "stored"}
    assert [h["phase"] for h in sf.history][:1] == ["real"]


def test_a_fit_through_8bit_codes_never_stores_worse(problem, tmp_path):
    """8-bit RGB codes fitted through their rounding: the PNG it writes reads back to its
    texels, at a loss no higher than the rounded codes of a float map (here, the exact one
    with a 2-degree tilt added, which the fit then corrects)."""
    prob, gt, prep = problem
    tilt = np.array([np.sin(np.radians(2.0)), 0.0, 0.0], np.float32)
    start = gt + tilt
    start /= np.linalg.norm(start, axis=-1, keepdims=True)
    sf = ST.fit_stored_map(prob, storage="rgb8", start=start, prepared=prep, rounds=1,
                           steps=3, cg_steps=10)
    from jaxnm import io as jio

    path = tmp_path / "stored.png"
    sf.save(path)
    raw, _ = jio.load_texture(path, channels=3)
    np.testing.assert_allclose(np.asarray(raw), sf.texels, atol=1e-6)
    assert sf.data.dtype == np.uint8 and sf.map_options.channels == 3
    assert sf.loss < 0.5 * sf.start_loss
    with pytest.raises(ValueError, match="unknown storage='bc7'"):
        ST.fit_stored_map(prob, storage="bc7", start=gt, prepared=prep)


def test_jaxnm_fit_store_bc5_writes_the_stored_map(tmp_path, capsys):
    """``jaxnm fit --store bc5`` writes normal_map.dds, which reads back to a map whose loss
    as stored report.json gives beside the fitted map compressed afterwards; a map whose
    size is not a multiple of 4 is refused before anything is fitted (one line, exit 2)."""
    import json

    from jaxnm.cli import main

    (tmp_path / "scene.json").write_text(json.dumps({
        "mesh": "builtin:plane", "width": 16, "height": 16,
        "camera": {"eye": [0, 0, 3], "target": [0, 0, 0]}}))
    rng = np.random.default_rng(0)
    targets = []
    for i, d in enumerate(([0.4, 0.1, 1], [-0.3, 0.3, 1], [0.0, -0.4, 1])):
        np.save(tmp_path / f"t{i}.npy", rng.uniform(0.3, 0.7, (16, 16, 3)).astype(np.float32))
        targets.append({"image": f"t{i}.npy", "lights": [{"type": "directional",
                                                          "direction": d}]})
    fit = {"scene": "scene.json", "targets": targets, "map": {"size": 8},
           "solver": {"max_steps": 2}}
    (tmp_path / "fit.json").write_text(json.dumps(fit))
    out = tmp_path / "out"
    assert main(["fit", str(tmp_path / "fit.json"), "-o", str(out), "--no-progress",
                 "--store", "bc5", "--checkpoint-every", "0"]) == 0
    assert "stored as bc5" in capsys.readouterr().out
    rep = json.loads((out / "report.json").read_text())["stored"]
    m = S.load_dds_normal_map(out / "normal_map.dds")
    assert m.texels.shape == (8, 8, 2) and rep["file"] == "normal_map.dds"
    # the loss the report gives is the file's, under the fit file's problem
    from jaxnm.config import load_fit

    prob = load_fit(tmp_path / "fit.json").problem
    args = ModelArgs.create(prepare(prob), reduce=True)
    loss = ST.stored_loss(m.texels, m.options(prob.sampling), args)
    np.testing.assert_allclose(loss, rep["loss"], rtol=1e-5)
    assert rep["loss"] <= rep["loss_compressed_afterwards"]
    fit["map"] = {"size": 6}
    (tmp_path / "fit.json").write_text(json.dumps(fit))
    assert main(["fit", str(tmp_path / "fit.json"), "-o", str(tmp_path / "out6"),
                 "--no-progress", "--store", "bc5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("jaxnm fit: error: ") and "multiple of 4" in err[-1], err
    assert not [line for line in err if line.startswith("preparing")], err
    assert not (tmp_path / "out6" / "report.json").exists()
