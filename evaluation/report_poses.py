"""The report's poses section: how the cameras were placed (the poses stage's artifact).

Cameras over the sparse points, the pair graph with its inlier counts (which pairs the
global solve kept), the method and why, the scale and its uncertainty, and the views left
out with the reason. Kept apart from evaluation/report.py, which calls `add_poses_section`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evaluation.report_text import fmt
from schemas.poses import PosesOutput


def plot_pair_graph(data: PosesOutput, path: Path) -> bool:
    """The placed cameras seen from above (world x right, z up the page) joined by the pairs
    the upright solver tried: kept pairs solid, their width and label the inliers; pairs it
    verified but dropped dashed red. False when there is nothing to draw."""
    poses = {v.view: np.asarray(v.pose) for v in data.views if v.registered and v.pose is not None}
    if not poses:
        return False
    from evaluation.visuals import pyplot

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 6))
    top = max([p.inliers for p in data.pairs] or [1])
    for p in data.pairs:
        if p.a not in poses or p.b not in poses or p.inliers == 0:
            continue
        a, b = poses[p.a][[0, 2], 3], poses[p.b][[0, 2], 3]
        style = {"color": "tab:blue", "lw": 0.5 + 3.0 * p.inliers / top} if p.used else \
            {"color": "tab:red", "lw": 0.8, "ls": "--"}
        ax.plot([a[0], b[0]], [a[1], b[1]], zorder=1, **style)
        mid = (a + b) / 2
        ax.annotate(str(p.inliers), mid, fontsize=6, color=style["color"], ha="center", va="center",
                    bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.7})
    for name, pose in poses.items():
        x, z = pose[0, 3], pose[2, 3]
        ax.plot(x, z, "o", color="black", ms=4, zorder=2)
        ax.annotate(name, (x, z), textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.set_aspect("equal")
    ax.set_xlabel("world x (m)")
    ax.set_ylabel("world z (m)")
    ax.set_title("pair graph: inliers per pair (solid: kept, dashed: dropped)")
    ax.grid(True, lw=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def add_poses_section(doc, run_dir: Path) -> bool:
    """Append the poses section to the report `doc` (evaluation.report_doc.ReportDoc); False (nothing
    added) when the run has no poses artifact, i.e. every pose came from scene.json."""
    from pipeline.engine import read_output

    data: PosesOutput | None = read_output(run_dir, "poses")
    if data is None:
        return False
    views = data.views
    placed = sum(v.registered for v in views)
    doc.h(2, "Poses", "poses")
    reason = data.method_reason
    doc.p(f"{placed} of {len(views)} views placed by {data.method}"
          + (f" (poses.method={data.requested_method}: {reason})" if reason else "")
          + f"; {data.scale_text()}; {data.points} sparse points"
          + (f", median angular residual {fmt(data.residual_deg, '.3f')}°" if data.residual_deg is not None
             else "") + ".")
    if data.left_out:
        doc.p("Left out: " + "; ".join(f"{k}: {why}" for k, why in data.left_out.items()) + ".", "warn")
    figures = []
    drawing = Path(run_dir) / "poses" / data.drawing
    if drawing.is_file():
        figures.append((drawing, "cameras over the sparse points (from above)"))
    graph = doc.img_dir / "poses-pair-graph.png"
    if data.pairs and plot_pair_graph(data, graph):
        figures.append((graph, "pair graph with inlier counts"))
    if figures:
        doc.images(figures, "poses")
    if len(data.attempts) > 1:
        doc.table(["method", "placed", "seconds", "outcome"],
                  [[a.method, str(a.placed), fmt(a.seconds, ".1f"), a.failure or "placed"]
                   for a in data.attempts])
    if data.pairs:
        doc.table(["pair", "inliers", "kept"],
                  [[f"{p.a} – {p.b}", str(p.inliers) if p.inliers else "not verified", fmt(p.used)]
                   for p in data.pairs])
    doc.table(["view", "placed", "given", "observations", "residual (px)"],
              [[v.view, fmt(v.registered), fmt(v.given), str(v.observations),
                fmt(v.reprojection_error_px, ".3g")] for v in views])
    return True
