"""PNG plots of a simulation's per-frame measurements (``warpskin simulate --report``).

Drawn with matplotlib (a dependency); where it cannot be imported (a broken install), only
``report.json`` is written and the run warns once on stderr.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_plots"]


def write_plots(report_dir: Path, metrics: dict, subvolume_names: list[str], *, title: str = "",
                where: tuple[np.ndarray, np.ndarray] | None = None,
                weights: tuple[np.ndarray, np.ndarray] | None = None, quality: dict | None = None) -> list[str]:
    """Write volume, sub-volume, energy, residual, offset, intersection, contact and step-time
    plots against the written frames (the bake's time codes), each titled with ``title`` (the
    scene and its parameters); with ``where = (rest points [V, 3], largest distance from LBS
    per vertex [V])``, also a picture of where the skin departs from LBS (front and side views
    of the rest pose, coloured by that distance); with ``weights = (rest points [N, 3], physics
    weight [N])`` of every written mesh, the physics-weight map the same way; with ``quality =
    {mesh: series}`` (:class:`~warpskin.quality.QualityLog`), each written mesh's strained edges
    (beside its LBS's) and flipped triangles per frame. Returns the file names (empty without
    matplotlib)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    t = np.array(metrics.get("frame") or metrics["time"])  # frames, as the DCC's timeline shows them
    frame_label = "frame" if metrics.get("frame") else "time [s]"
    written: list[str] = []

    def figure(name: str, what: str, xlabel: str, ylabel: str, draw, legend: bool = False) -> None:
        fig, ax = plt.subplots(figsize=(8, 4.5))
        draw(ax)
        ax.set(title=what, xlabel=frame_label if xlabel == "time [s]" else xlabel, ylabel=ylabel)
        if title:
            fig.suptitle(title, fontsize=8)
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
                            color=cmap(n / max(len(picks) - 1, 1)), label=f"{frame_label} {t[k]:g}")

        figure("residuals.png", "Iteration residuals", "elasticity iteration (last substep of the frame)",
               "largest position correction [m]", residuals, True)

    figure("offset_from_lbs.png", "How far the physical skin departs from LBS", "time [s]",
           "largest skin offset from LBS [mm]", lambda ax: ax.plot(t, 1e3 * np.array(metrics["max_offset_from_lbs"])))

    if metrics.get("intersecting_pairs"):
        def pairs(ax):
            ax.plot(t, metrics["intersecting_pairs"], label="warpskin", lw=2, drawstyle="steps-mid")
            ax.plot(t, metrics["intersecting_pairs_lbs"], label="LBS", lw=2, ls="--", drawstyle="steps-mid")

        figure("intersections.png", "Intersecting skin triangle pairs (exact check)", "time [s]", "pairs", pairs, True)

    if metrics.get("contacts_point_triangle"):
        def contacts(ax):
            ax.plot(t, metrics["contacts_point_triangle"], label="point-triangle contacts")
            ax.plot(t, metrics["contacts_edge_edge"], label="edge-edge contacts")
            ax.plot(t, metrics["constraints_active"], label="active constraints (last iteration)")

        figure("contacts.png", "Self-collision over the run", "time [s]", "count", contacts, True)

    def rest_map(name: str, rest: np.ndarray, values: np.ndarray, label: str, what: str, **scatter) -> None:
        """Front and side views of the rest pose, points coloured by ``values``."""
        order = np.argsort(values)  # the largest on top
        fig, axes = plt.subplots(1, 2, figsize=(10, 5.5))
        for ax, (a, b, view) in zip(axes, [(0, 1, "front (X, Y)"), (2, 1, "side (Z, Y)")]):
            sc = ax.scatter(rest[order, a], rest[order, b], c=values[order], **scatter)
            ax.set(title=view, aspect="equal")
            ax.set_xticks([])
            ax.set_yticks([])
        fig.colorbar(sc, ax=axes, label=label, shrink=0.8)
        fig.suptitle((title + "\n" if title else "") + what, fontsize=8)
        fig.savefig(report_dir / name, dpi=110)
        plt.close(fig)
        written.append(name)

    if where is not None and len(where[0]):
        rest_map("offset_map.png", np.asarray(where[0]), 1e3 * np.asarray(where[1]),
                 "largest distance from LBS over the run [mm]", "Where the physical skin departs from LBS (rest pose)",
                 s=6, cmap="inferno")

    if weights is not None and len(weights[0]):
        rest_map("physics_weight_map.png", np.asarray(weights[0]), np.asarray(weights[1], dtype=np.float64),
                 "physics weight (0: LBS, 1: physical)", "Physics weight of every written point (rest pose)",
                 s=4, cmap="viridis", vmin=0.0, vmax=1.0)

    if quality:
        tq = t[: min(len(t), min(len(v["strained"]) for v in quality.values()))]

        def strained(ax):
            for name, v in quality.items():
                line = ax.plot(tq, 100 * np.asarray(v["strained"][: len(tq)]), label=f"{name}")[0]
                ax.plot(tq, 100 * np.asarray(v["strained_lbs"][: len(tq)]), "--", color=line.get_color(),
                        label=f"{name} LBS")

        figure("written_strain.png", "Edges of the written meshes strained past 1.5x (dashed: LBS)", "time [s]",
               "% of edges", strained, True)

        def flipped(ax):
            for name, v in quality.items():
                ax.plot(tq, 100 * np.asarray(v["flipped"][: len(tq)]), label=name)

        figure("written_flips.png", "Triangles of the written meshes flipped against LBS", "time [s]",
               "% of triangles", flipped, True)

    if metrics.get("step_ms"):
        figure("step_time.png", "Time per solver step", "time [s]", "ms per step",
               lambda ax: ax.plot(t[1:], np.array(metrics["step_ms"])[1:]))
    return written
