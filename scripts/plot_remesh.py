#!/usr/bin/python3
"""Error against grid for `orthosim remesh` (issue 4), PNG, with Debian's python3-matplotlib.

    build-*/tests/remesh_bench --benchmark_filter=NONE --table_json=TABLE.json
    scripts/plot_remesh.py TABLE.json OUT.png

TABLE.json is remesh_bench's error-vs-grid table: a list of cases, each with rows
(nu, nv, h_mean_m, hausdorff_m, mean_m) for the grids 15x5 ... 400x100. The plot
shows the two-sided Hausdorff and mean distances of the quad surface to the input
against the mean quad edge h (log-log), with the fitted order per case and an
O(h^2) reference line through the finest Hausdorff point of the first case.
"""
import json
import math
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def fitted_order(h, e):
    lx = [math.log(x) for x in h]
    ly = [math.log(y) for y in e]
    n = len(lx)
    sx, sy = sum(lx), sum(ly)
    sxx = sum(x * x for x in lx)
    sxy = sum(x * y for x, y in zip(lx, ly))
    return (n * sxy - sx * sy) / (n * sxx - sx * sx)


def main(argv):
    if len(argv) != 3:
        sys.stderr.write("usage: plot_remesh.py TABLE.json OUT.png\n")
        return 2
    with open(argv[1]) as f:
        cases = json.load(f)
    # the layered phantom case repeats the skin's errors: plot distinct cases only
    cases = [c for c in cases if "layers" not in c["case"]]
    fig, ax = plt.subplots(figsize=(7.0, 5.0), dpi=120)
    colours = ["tab:blue", "tab:orange", "tab:green", "tab:red"]
    for k, c in enumerate(cases):
        rows = c["rows"]
        h = [r["h_mean_m"] * 1e3 for r in rows]
        hd = [r["hausdorff_m"] * 1e3 for r in rows]
        md = [r["mean_m"] * 1e3 for r in rows]
        col = colours[k % len(colours)]
        label = c["case"].split(",")[0]
        ax.loglog(h, hd, "o-", color=col,
                  label=f"{label}: Hausdorff (order {fitted_order(h, hd):.2f})")
        ax.loglog(h, md, "s--", color=col, mfc="none",
                  label=f"{label}: mean (order {fitted_order(h, md):.2f})")
        for r, x, y in zip(rows, h, hd):
            if k == 0:
                ax.annotate(f"{r['nu']}x{r['nv']}", (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
    if cases:
        rows = cases[0]["rows"]
        h = [r["h_mean_m"] * 1e3 for r in rows]
        h0, e0 = h[-1], rows[-1]["hausdorff_m"] * 1e3
        ax.loglog(h, [e0 * (x / h0) ** 2 for x in h], ":", color="grey", label="O(h^2) reference")
    ax.set_xlabel("mean quad edge h (mm)")
    ax.set_ylabel("distance quad surface <-> input (mm)")
    ax.set_title("orthosim remesh: error against grid (15x5 ... 400x100)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(argv[2])
    print("plot_remesh: wrote", argv[2])
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
