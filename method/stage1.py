"""Stage 1: the dynamic 2D Gaussian model rendered at a time, its loss, its mechanisms (the P split by
motion, the coarse-to-fine and time-window curricula, density control) and ``Stage1``, the object the
training loop (method/train.py) runs (paper section "Stage 1")."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import torch

from method import losses
from method.buffers import STAGE1
from method.checkpoints import build_net, scene_from_checkpoint, scene_state
from method.data import SceneData
from method.model.density import DensityStats, densify_and_prune, reset_opacity
from method.model.gaussians import GaussianAdam, Gaussians
from method.model.motion_basis import MotionBasis
from method.model.nodes import REFRESH_EVERY, MotionNodes
from method.model.scene import Deformed, DynamicScene, render
from method.optim import adam
from method.outputs import stage1_outputs
from method.schedules import expon_lr
from method.splat.camera import Camera
from method.splat.rasterize import RasterOutput


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
    x = scene.normalised(g.means)
    s_mu = torch.zeros(g.means.shape, dtype=torch.float64, device=g.means.device)
    s_sq = torch.zeros(len(g), dtype=torch.float64, device=g.means.device)
    s_rot = torch.zeros(g.quats.shape, dtype=torch.float64, device=g.quats.device)
    for t in times:
        d_mu, d_rot, _ = scene.field(x, float(t))
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
                         relative: bool = False, floor: float = 0.0) -> dict:
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

    ``floor``: Otsu sees motions below it as this value (``threshold`` None only). Why: the split is
    between two groups of the log motion, and a tail of nearly motionless Gaussians reaches 1e-7 and
    below; far out in log space, 3 % of them became Otsu's lower group once, and every other Gaussian was
    marked dynamic (BENCHMARKS.md, "The P split at the warm-up's end").
    Returns the threshold, the share marked static and the median motion of each group."""
    g = scene.g
    if scene.net is None or len(g) < 2:
        return {"static_share": 1.0}
    motion, mean_mu, mean_rot = motion_rms(scene, times)
    if relative:
        motion = motion * scene.extent / g.scales.max(-1).values.clamp_min(1e-12)
    if threshold is None:
        threshold = math.exp(otsu_threshold(motion.clamp_min(max(floor, 1e-12)).log()))
    static = motion < threshold
    g.t["means"][static] += mean_mu[static]
    g.t["quats"][static] += mean_rot[static]
    g.t["p_logit"].copy_(torch.where(static, -float(logit), float(logit)).to(g.t["p_logit"]))
    med = lambda m: float(motion[m].median()) if bool(m.any()) else 0.0  # noqa: E731
    return {"threshold": float(threshold), "static_share": float(static.float().mean()),
            "motion_static_median": med(static), "motion_dynamic_median": med(~static)}


def stage1_loss(out: RasterOutput, d: Deformed, rgb_gt: torch.Tensor, alpha_gt: torch.Tensor, cfg: dict,
                iteration: int, warmup: bool) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The weighted sum of the stage-1 terms and each term (unweighted) for the log."""
    s = cfg
    img = out.features[..., STAGE1.colour]
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


# ------------------------------------------------------------------ set-up, curricula, outputs

def mlp_lr(iteration: int, total: int, s1: dict) -> float:
    """The deformation network's rate: exponential decay from ``lr_mlp`` to ``lr_mlp * lr_mlp_final`` (paper)."""
    return expon_lr(iteration, total, s1["lr_mlp"], s1["lr_mlp"] * s1["lr_mlp_final"])


def carve(points: torch.Tensor, data: SceneData, fraction: float = 0.5) -> torch.Tensor:
    """Keep points that fall inside the foreground (alpha > 0.5) of at least ``fraction`` of the training
    views that see them (a visual hull; moving objects blur it, density control does the rest)."""
    inside = torch.zeros(points.shape[0])
    seen = torch.zeros(points.shape[0])
    for v in data.train:
        xi, yi, ok = pixel_of(points, v.camera)
        a = v.alpha[yi.to(v.alpha.device), xi.to(v.alpha.device)].cpu()
        seen += ok.cpu().float()
        inside += (ok.cpu() & (a > 0.5)).float()
    return (seen > 0) & (inside >= fraction * seen.clamp_min(1))


def pixel_of(points: torch.Tensor, cam: Camera) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The pixel (column, row; clamped into the image) each point's centre projects to, and whether it lands
    in the image in front of the camera."""
    p = points.to(cam.w2c) @ cam.w2c[:3, :3].T + cam.w2c[:3, 3]
    z = p[:, 2]
    x = cam.focal * p[:, 0] / z.clamp_min(1e-6) + cam.cx
    y = cam.focal * p[:, 1] / z.clamp_min(1e-6) + cam.cy
    ok = (z > 1e-3) & (x >= 0) & (x < cam.width) & (y >= 0) & (y < cam.height)
    return x.clamp(0, cam.width - 1).long(), y.clamp(0, cam.height - 1).long(), ok


@torch.no_grad()
def on_moving_objects(scene: DynamicScene, views) -> torch.Tensor | None:
    """Per Gaussian: is its centre, carried by the network to each training view's time (P = 1, as in the
    warm-up), on the generator's moving-object mask in most of the views that see it? None without masks.

    For the log only (the P split never sees it): it tells a run whose moving objects came out static
    whether the warm-up had put Gaussians on them at all, or the split marked the ones it had as static
    (BENCHMARKS.md, "The P split at the warm-up's end")."""
    if scene.net is None or not views or any(v.dynamic_mask is None for v in views):
        return None
    g = scene.g
    x = scene.normalised(g.means)
    on = torch.zeros(len(g), device=g.means.device)
    seen = torch.zeros(len(g), device=g.means.device)
    for v in views:
        d_mu, _, _ = scene.field(x, float(v.time))
        xi, yi, ok = pixel_of(g.means + d_mu.to(g.means), v.camera)
        m = v.dynamic_mask.to(g.means.device)
        on += (ok & (m[yi.to(m.device), xi.to(m.device)] > 0.5)).float()
        seen += ok.float()
    return (seen > 0) & (on > 0.5 * seen)


def split_check(moving: torch.Tensor, static: torch.Tensor) -> dict:
    """How the P split treated the Gaussians on the moving objects (``moving``) and the rest, given which it
    marked static: counts and the share of each group it put on the right side."""
    n_mov = int(moving.sum())
    return {"moving_gaussians": n_mov,
            "moving_marked_dynamic": float((moving & ~static).sum()) / max(n_mov, 1),
            "rest_marked_static": float((~moving & static).sum()) / max(int((~moving).sum()), 1)}


def c2f_factor(iteration: int, levels: int, until: int) -> int:
    """Image downscale factor at ``iteration`` of a coarse-to-fine schedule: 2^levels at the start, halving
    at evenly spaced iterations, 1 (full resolution) after ``until``; 1 throughout when either is 0.

    Why: the balls of `spheres` move by many pixels between frames, and a splat only receives gradient
    from pixels it covers; on a coarse image the same motion is a few pixels and a splat covers more of
    the object (the classic coarse-to-fine answer to large displacements), and a coarse step is cheaper."""
    if levels <= 0 or until <= 0 or iteration > until:
        return 1
    return 2 ** (levels - (max(iteration, 1) - 1) * levels // until)


def time_window_views(times: list[float], iteration: int, start: float, until: int,
                      front: bool = False) -> list[int]:
    """Indices of the training views a time-window curriculum may draw at ``iteration``: those whose time
    lies in the first ``start`` of the time range at iteration 1, the window growing linearly to the whole
    range at ``until``; every view when ``until`` is 0 or passed.

    Why: with one view per time, a Gaussian on a fast object at one time sits elsewhere at the others, so
    it only survives if the deformation already carries it along. Opening the times in order lets the
    network follow the object from a time it has fitted to the next, a small step, instead of having to
    find every position at once (spheres' small bouncing ball).

    ``front``: only the window's newest ``start`` share of the range (the times just opened), so that a
    caller can give them more draws than their share of a wide window."""
    if until <= 0 or iteration >= until:
        return list(range(len(times)))
    lo, hi = min(times), max(times)
    frac = start + (1.0 - start) * max(iteration - 1, 0) / until
    limit = lo + frac * (hi - lo)
    order = sorted(range(len(times)), key=lambda k: times[k])
    window = [k for k in order if times[k] <= limit + 1e-9]
    chosen = [k for k in window if times[k] >= limit - start * (hi - lo) - 1e-9] if front else window
    return chosen or window[-1:] or order[:1]


def downsampled(view, factor: int):
    """The view at 1/factor resolution: area-averaged image and alpha, the same camera with its focal
    length and size divided (pixel centres stay consistent since cx = width / 2)."""
    if factor == 1:
        return view
    cam = view.camera
    if cam.width % factor or cam.height % factor:
        return view
    pool = torch.nn.functional.avg_pool2d
    rgb = pool(view.rgb.permute(2, 0, 1)[None], factor)[0].permute(1, 2, 0).contiguous()
    alpha = pool(view.alpha[None, None], factor)[0, 0]
    small = Camera(cam.width // factor, cam.height // factor, cam.focal / factor, cam.w2c, cam.c2w)
    return dataclasses.replace(view, camera=small, rgb=rgb, alpha=alpha, dynamic_mask=None)


def init_points(data: SceneData, cfg: dict, gen: torch.Generator) -> torch.Tensor:
    s = cfg["stage1"]
    n = s["init_points"]
    c, e = data.center.cpu(), data.extent
    if not s["init_carve"]:
        return c + (torch.rand(n, 3, generator=gen) * 2 - 1) * e
    kept, tries = [], 0
    total = 0
    while total < n and tries < 20:
        cand = c + (torch.rand(4 * n, 3, generator=gen) * 2 - 1) * e
        k = cand[carve(cand, data)]
        kept.append(k)
        total += k.shape[0]
        tries += 1
    pts = torch.cat(kept)[:n] if total else c + (torch.rand(n, 3, generator=gen) * 2 - 1) * e
    return pts


def build_scene(data: SceneData, cfg: dict, static: bool, gen: torch.Generator, device: torch.device) -> DynamicScene:
    m = cfg["model"]
    pts = init_points(data, cfg, gen)
    g = Gaussians.from_points(pts, cfg["stage1"]["init_opacity"], m["p_init_logit"], gen,
                              scale_factor=cfg["stage1"]["init_scale"]).to(device)
    net = None if static else build_net(m).to(device)
    scene = DynamicScene(g, net, data.center.to(device), data.extent, m["p_temperature"], m["delta_colour"],
                         m["separation"])
    scene.model_cfg = dict(m)
    if net is not None and m["deform_nodes"]:
        scene.nodes = MotionNodes(m["deform_nodes"])
    return scene


def make_optimisers(scene: DynamicScene, cfg: dict) -> tuple[GaussianAdam, torch.optim.Optimizer | None]:
    s = cfg["stage1"]
    lrs = {"means": s["lr_position"] * scene.extent, "quats": s["lr_rotation"], "log_scales": s["lr_scaling"],
           "opacity_logit": s["lr_opacity"], "colour_logit": s["lr_colour"], "p_logit": s["lr_p"]}
    if "basis_logit" in scene.g.t:
        lrs["basis_logit"] = s["lr_basis_logit"]
    gopt = GaussianAdam(scene.g, lrs)
    nopt = adam(scene.net.parameters(), lr=s["lr_mlp"], eps=1e-15) if scene.net is not None else None
    return gopt, nopt


def basis_rates(scene: DynamicScene, s: dict) -> tuple[float, float]:
    """The motion bases' starting rates: (translations, x the scene extent; rotations)."""
    return s["lr_basis_translation"] * scene.extent, s["lr_basis_rotation"]


def basis_optimiser(scene: DynamicScene, s: dict) -> torch.optim.Optimizer:
    """Adam over the motion bases' translations and rotations (rates set each step in Stage1.forward)."""
    b = scene.basis
    lt, lq = basis_rates(scene, s)
    return adam([{"params": [b.trans], "lr": lt}, {"params": [b.quat], "lr": lq}], lr=0.0, eps=1e-15)


def basis_knots(times: list[float], count: int) -> list[float]:
    """``count`` evenly spaced times over the training times' range, where the motion bases are sampled.

    Why not every training time: there is one camera per time, so a basis sampled at each time is fitted
    by one view at each, free to slide its objects along that camera's rays; at spheres' test views (all
    at t = 0) the balls came out 3 dB worse than the network's while the training views fitted better
    (BENCHMARKS.md, "rigid motion bases"). A knot between several times is seen from several cameras."""
    if count < 2:
        raise ValueError(f"model.motion_knots must be at least 2, got {count}")
    lo, hi = min(times), max(times)
    return [lo + (hi - lo) * k / (count - 1) for k in range(count)]


@torch.no_grad()
def trajectories(scene: DynamicScene, times: list[float]) -> torch.Tensor:
    """(N, J, 3): every Gaussian's centre carried by the network to each of the times."""
    x = scene.normalised(scene.g.means)
    return torch.stack([scene.g.means + scene.field(x, float(t))[0].to(scene.g.means) for t in times], 1)



def evaluate_test(scene: DynamicScene, data: SceneData) -> float | None:
    """Mean PSNR of the test views (inference P, at each view's time), for the log and the bar."""
    if not data.test:
        return None
    vals = []
    with torch.no_grad():
        for v in data.test:
            out = render(scene.deform(v.time, p_mode="inference"), v.camera, data.background)
            vals.append(losses.psnr(out.features[..., STAGE1.colour].clamp(0, 1), v.rgb))
    return float(sum(vals) / len(vals))



class Stage1:
    """What stage 1 optimises and how one step goes, for the training loop (method/train.py).

    Optimises the canonical Gaussians (GaussianAdam) and the deformation network (Adam); each step draws
    a training view (from the time window while that curriculum runs, at the coarse-to-fine level of the
    iteration), renders the Gaussians at its time with P sampled (P = 1 in the warm-up), and takes the
    stage-1 loss. After the step: density control. At the warm-up's end: the P split by motion."""

    number = 1
    generator_offset = 0  # the stage's generator is seeded with seed + this
    forward_lap = "loss"  # the timer's name for the end of the forward

    def __init__(self, data: SceneData, cfg: dict, *, static: bool, device: torch.device):
        self.data, self.cfg, self.s = data, cfg, cfg["stage1"]
        self.static, self.device = bool(static), device
        self.scene: DynamicScene | None = None
        self.gopt: GaussianAdam | None = None
        self.nopt: torch.optim.Optimizer | None = None
        self.bopt: torch.optim.Optimizer | None = None  # the motion bases' (model.motion_bases), from the split on
        self.stats: DensityStats | None = None
        self.prior_seconds = self.prior_cpu_seconds = 0.0
        self.view_times = [float(v.time) for v in data.train]
        self.train_times = sorted(set(self.view_times))
        self._coarse: dict = {}  # (view, factor) -> the downsampled view of the coarse-to-fine schedule
        self._step: dict = {}    # what the current step's forward left for after_step and the log

    # -- set-up and checkpoints
    def start(self, gen: torch.Generator, log) -> None:
        self.scene = build_scene(self.data, self.cfg, self.static, gen, self.device)
        self.gopt, self.nopt = make_optimisers(self.scene, self.cfg)
        self.stats = DensityStats(len(self.scene.g), self.device)
        if self.s["eval_every"]:
            first = evaluate_test(self.scene, self.data)  # the baseline the learning curve starts from
            if first is not None:
                log({"iteration": 0, "test_psnr": first, "gaussians": len(self.scene.g)})

    def resume(self, ck: dict) -> None:
        self.scene = scene_from_checkpoint(ck, self.cfg, self.device)
        self.gopt, self.nopt = make_optimisers(self.scene, self.cfg)
        self.gopt.load_state_dict(ck["gopt"])
        if self.nopt is not None:
            self.nopt.load_state_dict(ck["nopt"])
        if self.scene.basis is not None:
            self.bopt = basis_optimiser(self.scene, self.s)
            self.bopt.load_state_dict(ck["bopt"])
        self.stats = DensityStats(len(self.scene.g), self.device)
        self.stats.load(ck["density"])

    def state(self) -> dict:
        return {**scene_state(self.scene), "gopt": self.gopt.state_dict(),
                "nopt": None if self.nopt is None else self.nopt.state_dict(),
                "bopt": None if self.bopt is None else self.bopt.state_dict(), "density": self.stats.state(),
                "static": self.scene.static}

    # -- one step
    def _view(self, it: int, gen: torch.Generator):
        s = self.s
        if s["time_window_until"] and it < s["time_window_until"]:
            front = s["time_window_front"] > 0 and float(torch.rand(1, generator=gen)) < s["time_window_front"]
            pool = time_window_views(self.view_times, it, s["time_window_start"], s["time_window_until"], front)
            k = pool[int(torch.randint(len(pool), (1,), generator=gen))]
        else:
            k = int(torch.randint(len(self.data.train), (1,), generator=gen))
        factor = c2f_factor(it, s["c2f_levels"], s["c2f_until"])
        if factor == 1:
            return self.data.train[k]
        if (k, factor) not in self._coarse:
            self._coarse[(k, factor)] = downsampled(self.data.train[k], factor)
        return self._coarse[(k, factor)]

    def forward(self, it: int, total: int, gen: torch.Generator, timer, log):
        s, scene = self.s, self.scene
        self.gopt.set_lr("means", expon_lr(it, total, s["lr_position"] * scene.extent,
                                           s["lr_position"] * scene.extent * s["lr_position_final"]))
        if self.nopt is not None:
            for grp in self.nopt.param_groups:
                grp["lr"] = mlp_lr(it, total, s)
        if self.bopt is not None:  # the bases carry the motion the network did: its decay, from their own rates
            for grp, base in zip(self.bopt.param_groups, basis_rates(scene, s)):
                grp["lr"] = expon_lr(it, total, base, base * s["lr_mlp_final"])
        view = self._view(it, gen)
        if s["p_from_motion"] and it == s["warmup"] + 1 and not scene.static and scene.separation:
            moving = on_moving_objects(scene, self.data.train)  # before the split bakes the offsets in
            bases = self.cfg["model"]["motion_bases"]
            knots = basis_knots(self.train_times, self.cfg["model"]["motion_knots"]) if bases else []
            traj = trajectories(scene, knots) if bases else None
            info = assign_p_from_motion(scene, self.train_times, None, s["p_from_motion_logit"],
                                        s["p_motion_relative"], s["p_motion_floor"])
            if moving is not None:
                info["check"] = split_check(moving, scene.g.t["p_logit"] < 0)
            self.gopt.reset_values("p_logit", scene.g.t["p_logit"].detach())
            if bases:
                scene.basis = MotionBasis(knots, bases, network=True).to(self.device)
                logits, info["motion_bases"] = scene.basis.fit(
                    scene.g.means.detach(), traj, scene.g.t["p_logit"] > 0, gen, s["basis_sharpness"],
                    scene.g.scales.detach().max(-1).values ** 2)
                self.gopt.add_tensor("basis_logit", logits, s["lr_basis_logit"])
                self.bopt = basis_optimiser(scene, s)
            log({"iteration": it, "p_from_motion": info})
        if scene.nodes is not None and it % REFRESH_EVERY == 0:
            scene.refresh_nodes()  # the means drift; a count change re-chooses them on its own
        warm = it <= s["warmup"]
        d = scene.deform(view.time, p_mode="ones" if warm else "sample", generator=gen)
        timer.lap("deform")
        densify_now = s["densify_from"] <= it <= s["densify_until"]
        offsets = torch.zeros(len(scene.g), 2, device=self.device, requires_grad=True) if densify_now else None
        out = render(d, view.camera, self.data.background, screen_offsets=offsets, depth_ratio=s["depth_ratio"])
        timer.lap("rasterize")
        loss, terms = stage1_loss(out, d, view.rgb, view.alpha, s, it, warm)
        self._step = {"view": view, "out": out, "offsets": offsets, "densify": densify_now}
        return loss, terms

    def guarded(self) -> list[tuple[str, list[torch.Tensor]]]:
        """(name, tensors) whose gradients and values the loop's NaN guard checks."""
        out = [(name, [t]) for name, t in self.scene.g.t.items()]
        if self.scene.net is not None:
            out.append(("the deformation network", list(self.scene.net.parameters())))
        if self.scene.basis is not None:
            out.append(("the motion bases", list(self.scene.basis.parameters())))
        return out

    def zero_grad(self) -> None:
        self.gopt.zero_grad()
        if self.nopt is not None:
            self.nopt.zero_grad(set_to_none=True)
        if self.bopt is not None:
            self.bopt.zero_grad(set_to_none=True)

    def optimiser_step(self, it: int, total: int) -> None:
        self.gopt.step()
        if self.nopt is not None:
            self.nopt.step()
        if self.bopt is not None:
            self.bopt.step()

    def after_step(self, it: int, gen: torch.Generator, timer) -> None:
        """Density control: gradient statistics in its window, clone/split/prune every densify_every."""
        s, st = self.s, self._step
        if st["densify"]:
            cam = st["view"].camera
            self.stats.add(st["offsets"].grad, st["out"].visible, st["out"].radii, cam.width, cam.height)
            if it % s["densify_every"] == 0 and it < s["densify_until"]:
                densify_and_prune(self.scene.g, self.gopt, self.stats, grad_threshold=s["densify_grad_threshold"],
                                  percent_dense=s["percent_dense"], extent=self.scene.extent,
                                  min_opacity=s["prune_opacity"], max_gaussians=s["max_gaussians"],
                                  max_screen_radius=large_splat_limit(it, cam, s), generator=gen)
            if s["opacity_reset_every"] and it % s["opacity_reset_every"] == 0:
                reset_opacity(self.scene.g, self.gopt)
        timer.lap("density")

    # -- progress and results
    def log_fields(self, it: int, total: int) -> dict:
        st, scene = self._step, self.scene
        rec = {"train_psnr": losses.psnr(st["out"].features[..., STAGE1.colour].detach().clamp(0, 1), st["view"].rgb),
               "gaussians": len(scene.g)}
        if not scene.static:  # how far the separation has gone: share of Gaussians with P > 0.5
            rec["p_dynamic_share"] = float((scene.p_inference().detach() > 0.5).float().mean())
        if self.s["eval_every"] and (it % self.s["eval_every"] == 0 or it == total):
            rec["test_psnr"] = self.last_test_psnr = evaluate_test(scene, self.data)
        return rec

    last_test_psnr: float | None = None

    def describe(self) -> str:
        p = self.last_test_psnr
        return (f"  test PSNR {p:.2f}" if p else "") + f"  N {len(self.scene.g)}"

    def timing_fields(self) -> dict:
        return {}

    def finish(self, run_dir: Path, seconds: float, write_outputs: bool, gen: torch.Generator) -> dict:
        scene = self.scene
        metrics = {"iterations": self.s["iterations"], "gaussians": len(scene.g), "parameters": scene.num_parameters(),
                   "gaussian_parameters": scene.g.num_parameters(),
                   "network_parameters": 0 if scene.net is None else scene.net.num_parameters(),
                   "static": scene.static, "seconds": seconds}
        if write_outputs:
            metrics.update(stage1_outputs(scene, self.data, run_dir))
        return metrics


def large_splat_limit(it: int, camera: Camera, s: dict) -> float | None:
    """The screen radius above which density control prunes a splat (3DGS: 20 px at 800 px), applied once
    the first opacity reset has happened, as in 3DGS; None (no such pruning) before it or without resets."""
    every = s["opacity_reset_every"]
    if not every or it <= every:
        return None
    return 20.0 * max(camera.height, camera.width) / 800.0
