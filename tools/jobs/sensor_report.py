"""The characterize report: the plots as PNG files and the figures as a Markdown page."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from trundle.logs.outputs import save_figure


def beam_noise_figure(angles: np.ndarray, std: np.ndarray) -> Figure:
    """Per-beam range noise (std, m, per beam angle, rad) while standing still, its median dashed."""
    fig = Figure(figsize=(8, 3.5), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    log_scale = bool(np.any(std > 0))  # a noiseless (simulated or quantised) laser has no log axis
    (ax.semilogy if log_scale else ax.plot)(np.degrees(angles), std * 1000, lw=0.8, label="noise std of each beam")
    ax.axhline(np.nanmedian(std) * 1000, color="k", ls="--", lw=0.8, label=f"median {np.nanmedian(std) * 1000:.1f} mm")
    ax.set(xlabel="beam angle (deg)", ylabel=f"noise std (mm{', log' if log_scale else ''})",
           title="Per-beam noise while standing still")
    ax.legend(loc="upper right")
    return fig


def sensitivity_figure(true: np.ndarray, measured: np.ndarray) -> Figure:
    """Measured against true range (m), with the line where they are equal."""
    keep = np.isfinite(true) & np.isfinite(measured)
    step = max(1, keep.sum() // 20000)
    fig = Figure(figsize=(5, 5), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.plot(true[keep][::step], measured[keep][::step], ",", alpha=0.4, label="readings")
    lim = [np.nanmin(true[keep]), np.nanmax(true[keep])]
    ax.plot(lim, lim, "k--", lw=0.8, label="measured = true")
    ax.set(xlabel="true value (m)", ylabel="measured (m)", title="Sensitivity: measured against true range")
    ax.legend(loc="upper left")
    return fig


def write_plots(folder: Path, plots: dict[str, Any]) -> list[str]:
    """The PNGs of ``plots`` (per-beam noise, sensitivity) in ``folder``; returns their file names."""
    figures = {"beam_noise": beam_noise_figure, "sensitivity": sensitivity_figure}
    names = []
    for name, draw in figures.items():
        if name in plots:
            save_figure(draw(*plots[name]), folder / f"{name}.png", dpi=110)
            names.append(f"{name}.png")
    return names


def markdown(figures: dict[str, Any], topic: str, plots: list[str]) -> str:
    """The report of ``topic``'s figures as Markdown: the sensor class, a table of every figure, the ``plots``."""
    lines = [f"# Sensor characteristics: `{topic}`", ""]
    cls = figures["class"]
    lines += [f"Class: **{cls['sense']}**, **{cls['energy']}**; application: {cls['application']}.", ""]

    def walk(prefix: str, value: Any) -> None:
        """One table row per leaf of ``value`` (dotted name ``prefix``), the sensor class left out."""
        if isinstance(value, dict):
            for k, v in value.items():
                walk(f"{prefix}.{k}" if prefix else k, v)
        elif prefix != "class" and not prefix.startswith("class."):
            lines.append(f"| {prefix} | {value:.6g} |" if isinstance(value, float) else f"| {prefix} | {value} |")

    lines += ["| quantity | value (SI) |", "|---|---|"]
    walk("", {k: v for k, v in figures.items() if k != "class"})
    lines += [""] + [f"![{p}]({p})" for p in plots]
    return "\n".join(lines) + "\n"
