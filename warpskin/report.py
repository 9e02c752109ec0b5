"""PNG plots of a simulation's per-frame measurements (``warpskin simulate --report``).

Needs matplotlib (``pip install 'warpskin[report]'``); without it, only ``report.json`` is
written and the summary says how to get the plots.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_plots"]


def write_plots(report_dir: Path, metrics: dict, subvolume_names: list[str]) -> list[str]:
    """Write volume, sub-volume, energy, residual and offset plots; returns the file names
    (empty without matplotlib)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    t = np.array(metrics["time"])
    written: list[str] = []

    def figure(name: str, title: str, xlabel: str, ylabel: str, draw, legend: bool = False) -> None:
        fig, ax = plt.subplots(figsize=(8, 4.5))
        draw(ax)
        ax.set(title=title, xlabel=xlabel, ylabel=ylabel)
        ax.grid(alpha=0.3)
        if legend:
            ax.legend(fontsize=7, ncol=2)
        fig.tight_layout()
        fig.savefig(report_dir / name, dpi=110)
        plt.close(fig)
        written.append(name)

    v0 = metrics["volume_rest"]

    def volume(ax):
        ax.plot(t, 100 * (np.array(metrics["volume"]) / v0 - 1), label="warpskin", lw=2)
        ax.plot(t, 100 * (np.array(metrics["volume_lbs"]) / v0 - 1), label="LBS", lw=2, ls="--")

    figure("volume.png", "Whole skin volume against the rest volume", "time [s]", "volume change [%]", volume, True)

    if metrics.get("subvolume"):
        sub, sub_lbs = np.array(metrics["subvolume"]), np.array(metrics["subvolume_lbs"])
        rest = np.array(metrics["subvolume_rest"])

        def subvolumes(ax):
            for s, name in enumerate(subvolume_names):
                line, = ax.plot(t, 100 * (sub[:, s] / rest[s] - 1), label=name)
                ax.plot(t, 100 * (sub_lbs[:, s] / rest[s] - 1), ls="--", color=line.get_color())

        figure("subvolumes.png", "Sub-volumes: warpskin (solid) and LBS (dashed)", "time [s]", "volume change [%]",
               subvolumes, True)

    figure("energy.png", "Kinetic energy of all particles", "time [s]", "kinetic energy [J]",
           lambda ax: ax.semilogy(t, np.maximum(np.array(metrics["kinetic_energy"]), 1e-12)))

    res = [(k, r) for k, r in enumerate(metrics.get("residuals", [])) if r]
    if res:
        picks = res[:: max(1, len(res) // 8)]

        def residuals(ax):
            cmap = plt.get_cmap("viridis")
            for n, (k, r) in enumerate(picks):
                ax.semilogy(np.arange(1, len(r) + 1), np.maximum(np.array(r), 1e-12),
                            color=cmap(n / max(len(picks) - 1, 1)), label=f"t = {t[k]:.2f} s")

        figure("residuals.png", "Iteration residuals", "elasticity iteration (last substep of the frame)",
               "largest position correction [m]", residuals, True)

    figure("offset_from_lbs.png", "How far the physical skin departs from LBS", "time [s]",
           "largest skin offset from LBS [mm]", lambda ax: ax.plot(t, 1e3 * np.array(metrics["max_offset_from_lbs"])))
    return written
