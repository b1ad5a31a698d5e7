"""The two scoring protocols: how masks, PSNR averaging and LPIPS input ranges are applied.

``lumimotion`` reproduces the published code's conventions: prediction and ground truth are both
multiplied by the ground-truth alpha and scored over the full image, PSNR is the mean of per-channel
PSNRs, LPIPS is fed images in [0, 1] as they are. ``strict`` scores only the foreground (alpha > 0.5):
PSNR and SSIM are averaged over foreground pixels, LPIPS sees both images with the background set to
black and is fed [-1, 1] as LPIPS was trained. Both protocols share the rest: albedo aligned by a
per-channel median ratio in linear space over the foreground of all test views, roughness MSE over the
foreground, relight scored with no per-image rescaling. Relight under ``lumimotion`` is the method's
relight with its albedo scaled per channel by that same ratio before shading (the authors'
scale_albedo_dynamic.py + base_color_scale; IRGS does the same), when the method provides one
(``relight_scaled/``); under ``strict`` the relight as the method predicts it, so a method that gets the
albedo's scale right itself shows it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lumibench.errors import UserError

PSNR_CAP_DB = 100.0  # identical images have infinite PSNR; results store this cap instead (JSON has no inf)
FOREGROUND_THRESHOLD = 0.5


@dataclass(frozen=True)
class Protocol:
    name: str
    masked_full_image: bool
    psnr_per_channel: bool
    lpips_input_range: str
    relight_albedo_scaled: bool  # score relight_scaled/ (the albedo scaled before shading) when present

    def describe(self) -> str:
        if self.masked_full_image:
            return ("lumimotion protocol: full image with prediction and ground truth multiplied by the GT alpha, "
                    "PSNR averaged per channel, LPIPS fed [0,1]")
        return "strict protocol: foreground only (GT alpha > 0.5), pooled PSNR, LPIPS fed [-1,1]"

    def score_rgb(self, pred: np.ndarray, gt: np.ndarray, alpha: np.ndarray, lpips_net: str) -> dict[str, float]:
        """PSNR / SSIM / LPIPS of one RGB pair (display space, [0, 1]) under this protocol."""
        return self.score_rgb_to_one([pred], gt, alpha, lpips_net)[0]

    def score_rgb_to_one(self, preds, gt: np.ndarray, alpha: np.ndarray, lpips_net: str) -> list[dict[str, float]]:
        """:meth:`score_rgb` of several predictions of one view against its ground truth; LPIPS in one batch,
        the ground truth's features taken once."""
        from benchmark import metrics

        a = alpha[..., :1].astype(np.float32)
        fg = None
        if not self.masked_full_image:
            fg = foreground(alpha)
            if not fg.any():
                raise UserError("a test view has no foreground pixel (GT alpha <= 0.5 everywhere)")
        g = gt * a if fg is None else gt * fg
        out, masked = [], []
        for pred in preds:
            if fg is None:
                p = pred * a
                psnr = metrics.psnr(p, g, per_channel=self.psnr_per_channel)
                ssim = metrics.ssim(p, g)
            else:
                p = pred * fg
                psnr = metrics.psnr(pred, gt, mask=fg, per_channel=self.psnr_per_channel)
                ssim = metrics.ssim(p, g, mask=fg)  # black background: no leak from outside
            out.append({"psnr": cap_psnr(psnr), "ssim": float(ssim)})
            masked.append(p)
        lps = metrics.lpips_to_one(masked, g, net=lpips_net, input_range=self.lpips_input_range)
        for o, lp in zip(out, lps):
            o["lpips"] = float(lp)
        return out


PROTOCOLS = {
    "lumimotion": Protocol("lumimotion", masked_full_image=True, psnr_per_channel=True, lpips_input_range="[0,1]",
                           relight_albedo_scaled=True),
    "strict": Protocol("strict", masked_full_image=False, psnr_per_channel=False, lpips_input_range="[-1,1]",
                       relight_albedo_scaled=False),
}


def get_protocol(name: str) -> Protocol:
    if name not in PROTOCOLS:
        raise UserError(f"unknown protocol '{name}' (known: {', '.join(PROTOCOLS)})")
    return PROTOCOLS[name]


def foreground(alpha: np.ndarray) -> np.ndarray:
    """Binary foreground (H x W x 1 float) from a coverage alpha."""
    return (alpha[..., :1] > FOREGROUND_THRESHOLD).astype(np.float32)


def cap_psnr(value: float) -> float:
    return float(min(value, PSNR_CAP_DB))
