"""Residual plots over the workspace (PNG, matplotlib Agg)."""
from __future__ import annotations

import numpy as np


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def row_metric(res: dict) -> tuple[np.ndarray, str]:
    """Per-row residual size: strut RMS where full poses exist, else position, else orientation."""
    s = res["struts"]
    if np.isfinite(s).any():
        return np.sqrt(np.nanmean(s ** 2, axis=1)), "strut residual RMS per pose (mm)"
    c = res["coords"]
    if np.isfinite(c[:, :3]).any():
        return np.sqrt(np.nansum(c[:, :3] ** 2, axis=1)), "position residual per pose (mm)"
    return np.sqrt(np.nansum(c[:, 3:] ** 2, axis=1)), "orientation residual per pose (deg)"


def workspace_before_after(path, panels: list[tuple[str, dict]], title: str) -> None:
    """Scatter of poses (x, y of the platform, base frame) coloured by residual size, one panel each."""
    plt = _plt()
    n = len(panels)
    cols = 2
    rows = (n + 1) // 2
    fig, axes = plt.subplots(rows, cols, figsize=(11, 4.6 * rows), squeeze=False)
    vals = [row_metric(r)[0] for _, r in panels]
    vmax = max(float(np.nanmax(v)) for v in vals if v.size) if vals else 1.0
    label = row_metric(panels[0][1])[1] if panels else ""
    for k, (name, res) in enumerate(panels):
        ax = axes[k // cols][k % cols]
        X = res["poses"]
        v = vals[k]
        sc = ax.scatter(X[:, 0], X[:, 1], c=v, s=18 + 60 * v / max(vmax, 1e-12), cmap="viridis", vmin=0, vmax=vmax)
        rms = float(np.sqrt(np.nanmean(v ** 2)))
        ax.set_title(f"{name}\nRMS {rms:.4g}")
        ax.set_xlabel("platform x (mm, base frame)")
        ax.set_ylabel("platform y (mm)")
        ax.set_aspect("equal", adjustable="datalim")
        fig.colorbar(sc, ax=ax, label=label)
    for k in range(n, rows * cols):
        axes[k // cols][k % cols].axis("off")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def struts_vs_reading(path, q: np.ndarray, before: dict, after: dict, title: str) -> bool:
    """Strut residual against the drive reading, per strut, before and after. False without strut residuals."""
    sb, sa = before["struts"], after["struts"]
    if not np.isfinite(sb).any():
        return False
    plt = _plt()
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5), sharey=True)
    for i in range(6):
        ax = axes[i // 3][i % 3]
        ax.plot(q[:, i], sb[:, i], "o", ms=3, alpha=0.6, label="baseline (rigid 42)")
        ax.plot(q[:, i], sa[:, i], "o", ms=3, alpha=0.8, label="extended")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_title(f"strut {i + 1}")
        ax.set_xlabel("reading q (mm)")
        if i % 3 == 0:
            ax.set_ylabel("strut residual (mm)")
    axes[0][0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True


def cause_plot(path, name: str, q: np.ndarray, X: np.ndarray, dl: np.ndarray, units_note: str) -> None:
    """One cause's strut-length contribution (mm): against the reading and over the workspace."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    ax = axes[0]
    for i in range(6):
        ax.plot(q[:, i], dl[:, i], "o", ms=3, label=f"strut {i + 1}")
    ax.set_xlabel("reading q (mm)")
    ax.set_ylabel("length contribution (mm)")
    ax.legend(fontsize=7, ncol=2)
    ax.set_title(f"{name}: contribution per strut")
    ax = axes[1]
    mag = np.sqrt(np.mean((dl - dl.mean(axis=0)) ** 2, axis=1))
    sc = ax.scatter(X[:, 0], X[:, 1], c=mag, cmap="magma", s=20)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("platform x (mm, base frame)")
    ax.set_ylabel("platform y (mm)")
    ax.set_title(f"{name}: RMS over struts (mean removed)")
    fig.colorbar(sc, ax=ax, label="mm")
    fig.suptitle(units_note, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def position_vectors(path, panels: list[tuple[str, dict]], title: str) -> bool:
    """Horizontal position residuals as arrows over the workspace, vertical ones as colour.

    One panel per model; arrows share one scale so before/after compare directly.
    False when x and y are not measured.
    """
    c0 = panels[0][1]["coords"]
    if not (np.isfinite(c0[:, 0]).any() and np.isfinite(c0[:, 1]).any()):
        return False
    plt = _plt()
    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 5.4), squeeze=False)
    big = max(float(np.nanmax(np.hypot(r["coords"][:, 0], r["coords"][:, 1]))) for _, r in panels)
    zmax = max(float(np.nanmax(np.abs(r["coords"][:, 2]))) if np.isfinite(r["coords"][:, 2]).any() else 0.0
               for _, r in panels) or 1.0
    for ax, (name, res) in zip(axes[0], panels):
        X, c = res["poses"], res["coords"]
        span = float(np.ptp(X[:, 0]) + np.ptp(X[:, 1])) / 2 or 1.0
        k = 0.08 * span / max(big, 1e-12)
        dz = np.nan_to_num(c[:, 2]) if np.isfinite(c[:, 2]).any() else np.zeros(len(c))
        sc = ax.scatter(X[:, 0], X[:, 1], c=dz, cmap="coolwarm", vmin=-zmax, vmax=zmax, s=14)
        ax.quiver(X[:, 0], X[:, 1], np.nan_to_num(c[:, 0]) * k, np.nan_to_num(c[:, 1]) * k,
                  angles="xy", scale_units="xy", scale=1.0, width=0.004)
        ax.set_title(f"{name}\narrow = x/y residual ({big:.3g} mm longest), colour = z residual")
        ax.set_xlabel("platform x (mm, base frame)")
        ax.set_ylabel("platform y (mm)")
        ax.set_aspect("equal", adjustable="datalim")
        fig.colorbar(sc, ax=ax, label="z residual (mm)")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True
