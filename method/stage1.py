"""Stage 1: the dynamic 2D Gaussian model rendered at a time, and its loss (paper section "Stage 1").

``DynamicScene`` bundles the canonical Gaussians, the deformation network (None for the static
pipeline), and the scene box that normalises positions for the network's encoding.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from method import losses
from method.model.deform import DeformNet, binary_concrete
from method.model.gaussians import Gaussians
from method.splat.camera import Camera
from method.splat.rasterize import RasterOutput, rasterize


@dataclass
class Deformed:
    """The Gaussians at one time: what the rasterizer and the tracer consume, plus the deltas."""

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colours: torch.Tensor
    p: torch.Tensor          # the P used (sampled in training, u = 0.5 at inference; ones in warm-up)
    d_mu: torch.Tensor
    d_col: torch.Tensor


class DynamicScene:
    def __init__(self, gaussians: Gaussians, net: DeformNet | None, center: torch.Tensor, extent: float,
                 temperature: float = 0.5, delta_colour: bool = True, separation: bool = True):
        self.g = gaussians
        self.net = net
        self.center = center
        self.extent = float(extent)
        self.temperature = float(temperature)
        self.delta_colour = bool(delta_colour)  # False: the wo_dc ablation
        self.separation = bool(separation)      # False: the wo_P ablation (P = 1 always)
        self.model_cfg: dict = {}                # the config's model section, saved in checkpoints

    @property
    def static(self) -> bool:
        return self.net is None

    def p_inference(self) -> torch.Tensor:
        return binary_concrete(self.g.t["p_logit"], self.temperature, training=False)

    def deform(self, t: float, *, p_mode: str = "inference", generator: torch.Generator | None = None,
               fixed_p: float | None = None, trunk_cache: dict | None = None) -> Deformed:
        """Gaussians at time ``t``. ``p_mode``: "sample" (training), "inference" (u = 0.5), "ones" (warm-up).

        ``trunk_cache`` (stage 2, where the canonical means, the network's trunk and its motion heads are
        frozen): the trunk's features and the motion per time are computed once and kept there; only the
        colour head runs each call. The same values as without it (the same operations, once)."""
        g = self.g
        means, quats, colours = g.means, g.quats, g.colours
        n = len(g)
        if self.net is None:
            zero = means.new_zeros(n, 3)
            return Deformed(means, quats, g.scales, g.opacities, colours, means.new_zeros(n), zero, zero)
        if fixed_p is not None:
            p = means.new_full((n,), float(fixed_p))
        elif not self.separation:
            p = means.new_ones(n)
        elif p_mode == "sample":
            p = binary_concrete(g.t["p_logit"], self.temperature, generator, training=True)
        elif p_mode == "ones":
            p = means.new_ones(n)
        else:
            p = self.p_inference()
        x = (means - self.center.to(means)) / self.extent
        if trunk_cache is None:
            d_mu, d_rot, d_col = self.net(x, t)
        else:
            trainable = [n for n, q in self.net.named_parameters() if q.requires_grad and not n.startswith("d_col.")]
            if means.requires_grad or trainable:
                raise ValueError("trunk_cache needs frozen means, trunk and motion heads "
                                 f"(trainable: {', '.join(trainable + (['means'] if means.requires_grad else []))})")
            key = float(t)
            if key not in trunk_cache:
                with torch.no_grad():
                    h = self.net.trunk(x, t)
                    trunk_cache[key] = (h, self.net.d_mu(h), self.net.d_rot(h))
            h, d_mu, d_rot = trunk_cache[key]
            d_col = torch.clamp_max(self.net.d_col(h), 1.0)
        if not self.delta_colour:
            d_col = torch.zeros_like(d_col)
        pc = p[:, None]
        return Deformed(means + pc * d_mu, quats + pc * d_rot, g.scales, g.opacities, colours * (1.0 - d_col),
                        p, d_mu, d_col)

    def num_parameters(self) -> int:
        return self.g.num_parameters() + (self.net.num_parameters() if self.net is not None else 0)


def otsu_threshold(values: torch.Tensor) -> float:
    """The split of 1-D values into two groups with the largest between-group variance (Otsu), exactly,
    over every split of the sorted values; the threshold is the midpoint of the two values beside it."""
    v = values.detach().flatten().double().sort().values
    n = v.numel()
    if n < 2:
        raise ValueError("otsu_threshold needs at least two values")
    k = torch.arange(1, n, dtype=v.dtype, device=v.device)  # size of the lower group
    head = v.cumsum(0)[:-1]
    mu0, mu1 = head / k, (v.sum() - head) / (n - k)
    between = (k / n) * (1 - k / n) * (mu0 - mu1) ** 2
    i = int(between.argmax())
    return float((v[i] + v[i + 1]) / 2)


@torch.no_grad()
def motion_rms(scene: DynamicScene, times: list[float]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per Gaussian: the RMS over ``times`` of its offset about the time-mean offset, as a fraction of the
    scene extent; and the time-mean offset and rotation delta. Running float64 sums, so memory stays one
    row per Gaussian whatever the number of times (150 times x 300k Gaussians at `full`)."""
    g = scene.g
    x = (g.means - scene.center.to(g.means)) / scene.extent
    s_mu = torch.zeros(g.means.shape, dtype=torch.float64, device=g.means.device)
    s_sq = torch.zeros(len(g), dtype=torch.float64, device=g.means.device)
    s_rot = torch.zeros(g.quats.shape, dtype=torch.float64, device=g.quats.device)
    for t in times:
        d_mu, d_rot, _ = scene.net(x, float(t))
        d_mu = d_mu.double()
        s_mu += d_mu
        s_sq += (d_mu * d_mu).sum(-1)
        s_rot += d_rot.double()
    n = float(len(times))
    mean_mu = s_mu / n
    var = (s_sq / n - (mean_mu * mean_mu).sum(-1)).clamp_min(0.0)
    return (var.sqrt() / scene.extent).to(g.means.dtype), mean_mu.to(g.means.dtype), (s_rot / n).to(g.quats.dtype)


@torch.no_grad()
def assign_p_from_motion(scene: DynamicScene, times: list[float], threshold: float | None, logit: float,
                         relative: bool = False) -> dict:
    """Start the separation from what the warm-up learned: a Gaussian whose offset barely changes over the
    training times is static, one that moves is dynamic.

    Why: during the warm-up (P = 1) every Gaussian follows the network, and static ones pick up small,
    nearly time-independent offsets. Lowering their P afterwards would undo those offsets (the rendering
    gets worse), so L_P has to fight the colour loss Gaussian by Gaussian, and at a few thousand
    iterations it settles halfway (BENCHMARKS.md). Here the time-mean offset and rotation delta of every
    Gaussian whose RMS motion is below the threshold is baked into its canonical state (its render at any
    time moves by at most that motion), and its logit is set to -``logit``; every other Gaussian's logit
    to +``logit``. L_P and the colour loss then train P as usual.

    ``threshold``: a fraction of the scene extent, or None for Otsu's split of the log motions. Why Otsu:
    how far the moving parts have moved by the warm-up's end differs between scenes by an order of
    magnitude (at `small`, spheres' balls 0.18 of the extent, the jumper 0.01, the static wobble 0.003 to
    0.005 in both), so no one constant separates both; the two groups are modes of the log motion.

    ``relative``: motion in units of each Gaussian's largest scale instead of the extent (and the
    threshold with it). Why: a wobble smaller than the splat itself barely changes what it draws, while
    a part that moves is carried several times its own size; a large wall splat dragged along by the
    network's smooth field beside a moving figure wobbles more in absolute terms than the figure's small
    splats do (BENCHMARKS.md, session 11).
    Returns the threshold, the share marked static and the median motion of each group."""
    g = scene.g
    if scene.net is None or len(g) < 2:
        return {"static_share": 1.0}
    motion, mean_mu, mean_rot = motion_rms(scene, times)
    if relative:
        motion = motion * scene.extent / g.scales.max(-1).values.clamp_min(1e-12)
    if threshold is None:
        threshold = math.exp(otsu_threshold(motion.clamp_min(1e-12).log()))
    static = motion < threshold
    g.t["means"][static] += mean_mu[static]
    g.t["quats"][static] += mean_rot[static]
    g.t["p_logit"].copy_(torch.where(static, -float(logit), float(logit)).to(g.t["p_logit"]))
    med = lambda m: float(motion[m].median()) if bool(m.any()) else 0.0  # noqa: E731
    return {"threshold": float(threshold), "static_share": float(static.float().mean()),
            "motion_static_median": med(static), "motion_dynamic_median": med(~static)}


def render(d: Deformed, camera: Camera, background: torch.Tensor, screen_offsets: torch.Tensor | None = None,
           extra: torch.Tensor | None = None) -> RasterOutput:
    """Rasterize colour and P (channel 3) plus optional extra features; the background fills colour only."""
    feats = [d.colours, d.p[:, None]] + ([extra] if extra is not None else [])
    f = torch.cat(feats, 1)
    bg = torch.cat([background.to(f), f.new_zeros(f.shape[1] - 3)])
    return rasterize(d.means, d.quats, d.scales, d.opacities, f, camera, bg, screen_offsets=screen_offsets)


def stage1_loss(out: RasterOutput, d: Deformed, rgb_gt: torch.Tensor, alpha_gt: torch.Tensor, cfg: dict,
                iteration: int, warmup: bool) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The weighted sum of the stage-1 terms and each term (unweighted) for the log."""
    s = cfg
    img = out.features[..., :3]
    lc, l1 = losses.colour_loss(img, rgb_gt, s["lambda_dssim"])
    terms = {"l_c": lc, "l1": l1}
    total = lc
    if s["lambda_normal"] > 0 and iteration >= s["normal_from"]:
        terms["normal"] = losses.normal_consistency(out.normal, out.normal_from_depth, out.alpha)
        total = total + s["lambda_normal"] * terms["normal"]
    if s["lambda_distortion"] > 0 and iteration >= s["distortion_from"]:
        terms["distortion"] = out.distortion.mean()
        total = total + s["lambda_distortion"] * terms["distortion"]
    if s["lambda_mask"] > 0:
        terms["mask"] = losses.mask_bce(out.alpha, alpha_gt)
        total = total + s["lambda_mask"] * terms["mask"]
    if d.d_mu.requires_grad or d.p.requires_grad:  # the dynamic terms (absent in the static pipeline)
        if not warmup and s["lambda_p"] > 0 and d.p.requires_grad:
            terms["p"] = losses.p_l1(d.p)
            total = total + s["lambda_p"] * terms["p"]
        if s["lambda_dc"] > 0 and d.d_col.requires_grad:
            terms["dc"] = losses.mean_sq_norm(d.d_col)
            total = total + s["lambda_dc"] * terms["dc"]
        if s["lambda_dmu"] > 0:
            terms["dmu"] = losses.mean_sq_norm(d.d_mu)
            total = total + s["lambda_dmu"] * terms["dmu"]
    return total, terms
