"""`python -m method demo` (`make demo`): dataset -> both stages -> relit test views -> scores against the
two floors -> a table and a picture sheet (ground truth vs ours: albedo, roughness, relit image, env map)."""
from __future__ import annotations

import argparse
from pathlib import Path

DEMO_GRID = Path(__file__).resolve().parents[2] / "configs" / "benchmark" / "demo.yaml"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="the whole chain on the embedded default scene, with a table and a picture sheet",
                       description="Render the demo profile's dataset of the default scene (configs/benchmark/"
                                   "demo.yaml), train LumiMotion (both stages), relight the test views, score it "
                                   "and the two floors, and write a table, a report and a picture sheet under "
                                   "OUT/<profile>/.")
    p.add_argument("--data", default="data")
    p.add_argument("--runs", default="runs")
    p.add_argument("--out", default="results", help="results root (default results; writes OUT/demo/)")
    p.add_argument("--jobs", type=int, default=None,
                   help="render worker processes (default: one per usable core, at most 4; each Blender then "
                        "gets the cores shared out, which renders the demo's 64 px frames faster than one "
                        "Blender on every core, and each worker builds the scene once, so more than a few "
                        "only add builds for its 123 frames)")


def run(args: argparse.Namespace) -> int:
    from benchmark.__main__ import main as benchmark_main
    from benchmark.config import load_benchmark_config
    from generator import pipeline
    from lumibench.errors import UserError
    from lumibench.machine import usable_cores

    grid = load_benchmark_config(DEMO_GRID)
    scene, conf = grid.scenes[0], grid.configurations[0]
    jobs = min(usable_cores(), 4) if args.jobs is None else args.jobs
    if jobs < 1:
        raise UserError(f"--jobs must be at least 1, got {jobs}")
    scene_dir = pipeline.render_scene(scene, grid.profile, Path(args.data), jobs=jobs, progress=True)
    rc = benchmark_main(["eval", "--config", str(DEMO_GRID), "--data", args.data, "--runs", args.runs,
                         "--results", args.out])
    out = Path(args.out) / grid.profile
    method = grid.methods[0]  # LumiMotion at the demo's budget (configs/benchmark/demo.yaml), then the floors
    pred = Path(args.runs) / grid.profile / method / scene / conf.train / "seed0" / "predictions"
    if not (pred / "meta.json").is_file():
        raise UserError(f"LumiMotion produced no predictions (see {out}/report.html and the job's error.log)")
    sheet = demo_sheet(scene_dir, pred, conf.train, conf.test, out / "demo_sheet.png")
    print(f"dataset:  {scene_dir}")
    print(f"run:      {pred.parent}")
    print(f"table:    {out / 'table.md'}")
    print(f"report:   {out / 'report.html'}")
    print(f"sheet:    {sheet}")
    table = out / "table.md"
    if table.is_file():
        print(table.read_text())
    return rc


def demo_sheet(scene_dir: Path, pred: Path, train: str, test: str, path: Path) -> Path:
    """Rows: test views. Columns: albedo GT / ours, roughness GT / ours, relit under the test light GT /
    ours; last row: the train light's env map, GT and estimated (clipped to [0, 1] and scaled to max 1)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from lumibench.predictions import PredictionFolder
    from lumibench.groundtruth import read_gt, read_lit
    from generator.envmap import read_envmap
    from lumibench import layout
    from lumibench.color import linear_to_srgb

    pf = PredictionFolder(pred)
    frames = layout.read_transforms(scene_dir, "test").frames[:4]
    # the relight the primary protocol (lumimotion) scores: with the albedo scaled as the benchmark aligns it
    relit = "relight_scaled" if pf.has("relight_scaled", test) else "relight"
    cols = ["albedo GT", "albedo ours", "roughness GT", "roughness ours", f"{test} GT",
            f"{test} ours (relit)" + ("\nalbedo scaled" if relit == "relight_scaled" else "")]
    fig, axes = plt.subplots(len(frames) + 1, len(cols), figsize=(2 * len(cols), 2 * (len(frames) + 1)))
    for i, f in enumerate(frames):
        rgb, alpha = read_lit(scene_dir, test, f.file_path)
        shape = alpha.shape[:2]
        a = alpha[..., :1]
        imgs = [linear_to_srgb(np.clip(read_gt(scene_dir, "albedo", f.file_path), 0, 1)) * a,
                pf.read("albedo", f.stem, shape) * a,
                np.repeat(read_gt(scene_dir, "roughness", f.file_path), 3, -1) * a,
                np.repeat(pf.read("roughness", f.stem, shape), 3, -1) * a,
                rgb * a, pf.read(relit, f.stem, shape, test) * a]
        for j, img in enumerate(imgs):
            axes[i, j].imshow(np.clip(img, 0, 1), interpolation="nearest")
            axes[i, j].set_axis_off()
            if i == 0:
                axes[i, j].set_title(cols[j], fontsize=9)
    gt_env = read_envmap(layout.envmap_path(scene_dir, train))
    est = pf.envmap(train)
    panels = [("GT env, clipped", np.clip(gt_env, 0, 1)), ("GT env / max", gt_env / max(gt_env.max(), 1e-8))]
    if est is not None:
        panels += [("estimated, clipped", np.clip(est, 0, 1)), ("estimated / max", est / max(est.max(), 1e-8))]
    for j in range(len(cols)):
        ax = axes[-1, j]
        ax.set_axis_off()
        if j < len(panels):
            ax.imshow(linear_to_srgb(np.clip(panels[j][1], 0, 1)), interpolation="nearest")
            ax.set_title(panels[j][0], fontsize=8)
    fig.suptitle(f"LumiMotion demo: {scene_dir.name}, trained under {train}, relit under {test}", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(path)
    return path
