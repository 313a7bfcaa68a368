"""Figures (PNG, matplotlib with the Agg backend). Called on one rank."""
from __future__ import annotations

import os

import numpy as np


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_stiffness_sweep(path: str, ks, omega, k_auto: float, label: str, omega_free: float,
                         omega_pinned: float) -> None:
    """The paper's Fig. 2: the first frequency against the spring stiffness, the auto k marked."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=120)
    ax.semilogx(ks, omega, "o-", ms=3, color="C0", label=r"$\omega(k)$ (FE + SLEPc)")
    ax.axhline(omega_free, color="0.5", ls=":", lw=1, label=r"$k \to 0$: no spring")
    ax.axhline(omega_pinned, color="0.5", ls="--", lw=1, label=r"$k \to \infty$: pinned")
    ax.axvline(k_auto, color="C3", lw=1.2, label=f"auto k = {k_auto:.3g} N/m")
    ax.set_xlabel("spring stiffness k [N/m]")
    ax.set_ylabel(r"natural frequency $\omega$ [rad/s]")
    ax.set_title(f"Spring at {label}: the frequency between its two limits")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    tmp = f"{path}.tmp-{os.getpid()}.png"
    fig.savefig(tmp)
    plt.close(fig)
    os.replace(tmp, path)
