#!/usr/bin/python3
"""Plots of `orthosim bench` results (issue 10), PNG, with Debian's python3-matplotlib.

    scripts/plot_bench.py RESULTS.json OUTDIR

Writes into OUTDIR:
  time_vs_error_<stage>.png   per stage: wall time (median, min-max bars) against the
                              error metric, ours and the peer, one colour per workload
  fig3a_msm_step_vs_grid.png  the paper's Fig. 3(a): time per mass-spring step against
                              nodes for 15x5 ... 400x100 grids, 4 layers
  fig3b_sph_step_vs_particles.png  Fig. 3(b): time per SPH substep against particles
  stability_matrix.png        stable / recovered / failed runs per dt x K2/K1 per integrator
Figures whose rows are absent (stage not run) are skipped.
"""
import json
import math
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def finite(v):
    return v is not None and isinstance(v, (int, float)) and math.isfinite(v) and v > 0


def machine_line(res):
    m = res.get("machine", {})
    return "%s, %s cores, %s, %s, commit %s, load %s" % (
        m.get("cpu", "?"), m.get("cores", "?"), m.get("compiler", "?").split(" (")[0],
        m.get("build_type", "?"), m.get("commit", "?"), (m.get("load_average_before") or "?").split(" ")[0])


def save(fig, res, path):
    fig.text(0.01, 0.005, machine_line(res), fontsize=6, color="0.4")
    fig.tight_layout(rect=(0, 0.02, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print("plot_bench: wrote", path)


def time_vs_error(res, stage, rows, out):
    rows = [r for r in rows if r["error_metric"] and r["error_value"] is not None and r["time_median_s"] is not None]
    if not rows:
        return
    fig, ax = plt.subplots(figsize=(7.5, 5))
    workloads = []
    for r in rows:
        if r["workload"] not in workloads:
            workloads.append(r["workload"])
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    log_x = all(finite(r["error_value"]) for r in rows)
    for i, w in enumerate(workloads):
        c = colours[i % len(colours)]
        ws = [r for r in rows if r["workload"] == w]
        xs = [r["error_value"] for r in ws]
        ys = [r["time_median_s"] for r in ws]
        lo = [max(0, r["time_median_s"] - (r["time_min_s"] or r["time_median_s"])) for r in ws]
        hi = [max(0, (r["time_max_s"] or r["time_median_s"]) - r["time_median_s"]) for r in ws]
        label = w.rsplit(": ", 1)[-1] if len(w) > 60 and ": " in w else w
        label = label if len(label) < 70 else label[:67] + "..."
        ax.errorbar(xs, ys, yerr=[lo, hi], fmt="o", color=c, label=label, capsize=2)
        for r in ws:
            ax.annotate(r["setting"], (r["error_value"], r["time_median_s"]), fontsize=6, xytext=(3, 3),
                        textcoords="offset points")
        peers = [r for r in ws if r["peer"] and r["peer_time_median_s"] is not None and r["peer_error_value"] is not None]
        if peers:
            ax.scatter([r["peer_error_value"] for r in peers], [r["peer_time_median_s"] for r in peers], marker="x",
                       color=c, label="peer: " + peers[0]["peer"])
            for r in peers:
                if not finite(r["peer_error_value"]):
                    log_x = False
    metrics = sorted({r["error_metric"] for r in rows})
    ax.set_xlabel("; ".join(metrics) if len(metrics) < 3 else "error (per workload)")
    ax.set_ylabel("wall time (s), median and min-max")
    if log_x:
        ax.set_xscale("log")
    if all(finite(r["time_median_s"]) for r in rows):
        ax.set_yscale("log")
    ax.set_title("%s: run time against error" % stage)
    ax.legend(fontsize=6, loc="best")
    ax.grid(True, which="both", alpha=0.3)
    save(fig, res, os.path.join(out, "time_vs_error_%s.png" % stage))


def scaling(res, rows, prefix, xlabel, title, path):
    rows = [r for r in rows if r["workload"].startswith(prefix) and finite(r["x"]) and finite(r["time_median_s"])]
    if not rows:
        return
    fig, ax = plt.subplots(figsize=(7, 5))
    workloads = []
    for r in rows:
        if r["workload"] not in workloads:
            workloads.append(r["workload"])
    for w in workloads:
        ws = sorted([r for r in rows if r["workload"] == w], key=lambda r: r["x"])
        xs = [r["x"] for r in ws]
        ys = [1e3 * r["time_median_s"] for r in ws]
        lo = [1e3 * (r["time_median_s"] - (r["time_min_s"] or r["time_median_s"])) for r in ws]
        hi = [1e3 * ((r["time_max_s"] or r["time_median_s"]) - r["time_median_s"]) for r in ws]
        ax.errorbar(xs, ys, yerr=[lo, hi], marker="o", capsize=2, label=w.split(", ", 1)[-1] if ", " in w else w)
        for r in ws:
            ax.annotate(r["setting"].replace(" particles", ""), (r["x"], 1e3 * r["time_median_s"]), fontsize=6,
                        xytext=(3, -9), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("ms per step (median, min-max)")
    ax.set_title(title)
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    save(fig, res, path)


def stability(res, rows, path):
    rows = [r for r in rows if r["workload"].startswith("stability matrix: ")]
    if not rows:
        return
    modes = []
    for r in rows:
        if r["extra"]["integrator"] not in modes:
            modes.append(r["extra"]["integrator"])
    dts = sorted({r["extra"]["dt_s"] for r in rows})
    krs = sorted({r["extra"]["stiffness_ratio"] for r in rows})
    fig, axes = plt.subplots(1, len(modes), figsize=(4.2 * len(modes), 4.2), squeeze=False)
    green, yellow, red = (0.2, 0.7, 0.3), (0.95, 0.8, 0.2), (0.85, 0.2, 0.2)
    for ax, mode in zip(axes[0], modes):
        img = [[(1, 1, 1)] * len(krs) for _ in dts]
        for r in rows:
            e = r["extra"]
            if e["integrator"] != mode:
                continue
            i, j = dts.index(e["dt_s"]), krs.index(e["stiffness_ratio"])
            n = max(1, e["runs"])
            img[i][j] = tuple((e["stable"] * g + e["recovered"] * y + e["failed"] * rr) / n
                              for g, y, rr in zip(green, yellow, red))
            ax.text(j, i, "%d/%d/%d" % (e["stable"], e["recovered"], e["failed"]), ha="center", va="center", fontsize=7)
        ax.imshow(img, aspect="auto")
        ax.set_xticks(range(len(krs)))
        ax.set_xticklabels(["%g" % k for k in krs], fontsize=7)
        ax.set_yticks(range(len(dts)))
        ax.set_yticklabels(["%.3g" % d for d in dts], fontsize=7)
        ax.set_xlabel("stiffness ratio K2/K1")
        ax.set_ylabel("dt (s)")
        ax.set_title(mode, fontsize=9)
    fig.suptitle("stability: stable / recovered / failed runs per cell (green / yellow / red)", fontsize=9)
    save(fig, res, path)


def main():
    if len(sys.argv) != 3:
        sys.stderr.write("usage: plot_bench.py RESULTS.json OUTDIR\n")
        return 2
    with open(sys.argv[1]) as f:
        res = json.load(f)
    out = sys.argv[2]
    rows = res.get("rows", [])
    stages = []
    for r in rows:
        if r["stage"] not in stages:
            stages.append(r["stage"])
    for s in stages:
        # the scaling and stability rows have their own figures
        rs = [r for r in rows if r["stage"] == s and not r["workload"].startswith(("stability matrix", "time per step against grid", "time per SPH substep"))]
        time_vs_error(res, s, rs, out)
    scaling(res, [r for r in rows if r["stage"] == "runtime"], "time per step against grid", "nodes (grids 15x5 ... 400x100, 4 layers)",
            "Fig. 3(a): time per mass-spring step against grid size", os.path.join(out, "fig3a_msm_step_vs_grid.png"))
    scaling(res, [r for r in rows if r["stage"] == "sph"], "time per SPH substep", "particles",
            "Fig. 3(b): time per SPH step against particles", os.path.join(out, "fig3b_sph_step_vs_particles.png"))
    stability(res, rows, os.path.join(out, "stability_matrix.png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
