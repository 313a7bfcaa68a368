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


def plot_run(path: str, folder: str) -> list:
    """The paper's figures for one run's HDF5 output, as PNGs in `folder`; returns the files written.

    Per constraint j: time history (Figs. 4, 7), phase diagram (Figs. 5, 8, 12), force (Fig. 10).
    Beam snapshots with the constraints and their deadbands (Figs. 6, 9, 11, 13).
    """
    import h5py

    plt = _pyplot()
    written = []

    def save(fig, name):
        target = os.path.join(folder, name)
        tmp = f"{target}.tmp-{os.getpid()}.png"
        fig.tight_layout()
        fig.savefig(tmp)
        plt.close(fig)
        os.replace(tmp, target)
        written.append(target)

    with h5py.File(path, "r") as f:
        t = f["time"][:]
        positions = f["constraints/position"][:]
        z, v, force = (f[f"constraints/{n}"][:] for n in ("displacement", "velocity", "force_peak"))
        d_minus = f["constraints/clearance_minus"][:] if "constraints/clearance_minus" in f else None
        d_plus = f["constraints/clearance_plus"][:] if "constraints/clearance_plus" in f else None
        for j, x in enumerate(positions):
            where = f"x = {x:g} m" if float(x) != int(x) or x < 1 else f"constraint {j + 1}"
            fig, ax = plt.subplots(figsize=(7, 3.6), dpi=120)
            ax.plot(t, z[:, j] * 1e3, lw=0.8, color="C0")
            if d_minus is not None:
                for level in (-d_minus[j], d_plus[j]):
                    ax.axhline(level * 1e3, color="C3", ls="--", lw=0.8)
            ax.set_xlabel("time t [s]")
            ax.set_ylabel(f"w({where.split(' = ')[-1] if 'x' in where else where}, t) [mm]")
            ax.set_title(f"Displacement at the constraint ({where}); dashed: clearance")
            ax.grid(alpha=0.3)
            save(fig, f"time_history_{j + 1}.png")

            fig, ax = plt.subplots(figsize=(5.2, 4.4), dpi=120)
            ax.plot(z[:, j] * 1e3, v[:, j], lw=0.6, color="C0")
            ax.set_xlabel("displacement w [mm]")
            ax.set_ylabel("velocity dw/dt [m/s]")
            ax.set_title(f"Phase diagram at {where}")
            ax.grid(alpha=0.3)
            save(fig, f"phase_{j + 1}.png")

            fig, ax = plt.subplots(figsize=(7, 3.6), dpi=120)
            ax.plot(t, force[:, j], lw=0.8, color="C2")
            ax.set_xlabel("time t [s]")
            ax.set_ylabel("constraint force N [N]")
            ax.set_title(f"Constraint force at {where} (peak over each sample interval)")
            ax.grid(alpha=0.3)
            save(fig, f"force_{j + 1}.png")

        if f["snapshots/w"].shape[0]:
            xs, ws, ts = f["snapshots/x"][:], f["snapshots/w"][:], f["snapshots/time"][:]
            fig, ax = plt.subplots(figsize=(7.5, 4.2), dpi=120)
            colors = plt.cm.viridis(np.linspace(0, 1, ws.shape[0]))
            for w, c in zip(ws, colors):
                ax.plot(xs, w * 1e3, color=c, lw=0.7)
            for j, x in enumerate(positions):
                ax.axvline(x, color="k", lw=0.6, alpha=0.6)
                if d_minus is not None:
                    ax.plot([x, x], [-d_minus[j] * 1e3, d_plus[j] * 1e3], color="C3", lw=3, alpha=0.7)
            ax.set_xlabel("position x [m]")
            ax.set_ylabel("total displacement w [mm]")
            ax.set_title(f"{ws.shape[0]} snapshots, t = {ts[0]:g} ... {ts[-1]:g} s "
                         f"(vertical: constraints, red: deadband)")
            ax.grid(alpha=0.3)
            sm = plt.cm.ScalarMappable(cmap="viridis", norm=plt.Normalize(ts[0], ts[-1]))
            fig.colorbar(sm, ax=ax, label="t [s]")
            save(fig, "snapshots.png")
    return written


def plot_sweep(path: str, folder: str) -> list:
    """Statistics of a sweep summary against each numeric parameter that varies, one line per
    combination of the other varying parameters (and sweep direction): the peak displacement at
    each constraint and probe (a frequency response when the parameter is the excitation
    frequency), impact rate, contact fraction and peak force."""
    import json

    import h5py

    plt = _pyplot()
    written = []
    with h5py.File(path, "r") as f:
        ok = np.array([s in (b"ok", "ok") for s in f["cases/status"][:]])
        stats = {name: f[f"cases/stats/{name}"][:] for name in
                 ("displacement_peak", "impact_rate", "contact_fraction", "force_peak")}
        probe_peak = f["cases/probe_peak"][:]
        columns = {}
        for name in json.loads(f.attrs["sweep"])["parameters"]:
            raw = f[f"cases/parameters/{name}"][:]
            columns[name] = raw if raw.dtype.kind == "f" else np.array([json.loads(v) for v in raw], dtype=object)
    varying = [n for n, v in columns.items() if len({repr(x) for x in v}) > 1]
    for name in varying:
        x = columns[name]
        if x.dtype.kind != "f":
            continue
        others = [n for n in varying if n != name]
        keys = [tuple(columns[n][i] for n in others) for i in range(x.size)]
        series = list(dict.fromkeys(keys))
        fig, axes = plt.subplots(2, 2, figsize=(10, 7), dpi=110, sharex=True)
        panels = [("displacement_peak", "peak |w| [mm]", 1e3), ("impact_rate", "impacts per second [1/s]", 1),
                  ("contact_fraction", "fraction of time in contact", 1), ("force_peak", "peak force [N]", 1)]
        for ax, (stat, label, scale) in zip(axes.ravel(), panels):
            for k, key in enumerate(series):
                sel = np.array([kk == key for kk in keys]) & ok & np.isfinite(x)
                order = np.flatnonzero(sel)[np.argsort(x[sel], kind="stable")]
                tag = ", ".join(f"{n.split('.')[-1]} {v}" for n, v in zip(others, key))
                tag = f" ({tag})" if tag else ""
                style = "v--" if "down" in key else "o-"
                table = stats[stat][order] * scale
                if table.shape[1] > 4:  # many supports: their mean and the worst one, not a line each
                    ax.plot(x[order], np.nanmean(table, axis=1), style, ms=3, lw=1, color=f"C{k % 10}",
                            label=f"mean over constraints{tag}")
                    ax.plot(x[order], np.nanmax(table, axis=1), style, ms=3, lw=1, color=f"C{k % 10}",
                            alpha=0.5, label=f"max over constraints{tag}")
                    columns_drawn = 1
                else:
                    for j in range(table.shape[1]):
                        ax.plot(x[order], table[:, j], style, ms=3, lw=1, color=f"C{(k + j) % 10}",
                                label=f"constraint {j + 1}{tag}")
                    columns_drawn = table.shape[1]
                if stat == "displacement_peak":
                    for p in range(probe_peak.shape[1]):
                        ax.plot(x[order], probe_peak[order, p] * 1e3, style, ms=3, lw=1.5, alpha=0.6,
                                color=f"C{(k + columns_drawn + p) % 10}", label=f"probe {p + 1}{tag}")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        for ax in axes[1]:
            ax.set_xlabel(name)
        if len(axes[0, 0].get_legend_handles_labels()[1]) <= 12:
            axes[0, 0].legend(fontsize=7)
        fig.suptitle(f"Sweep over {name} ({int(ok.sum())} of {ok.size} cases ran)")
        fig.tight_layout()
        target = os.path.join(folder, f"sweep_{name.replace('.', '_')}.png")
        tmp = f"{target}.tmp-{os.getpid()}.png"
        fig.savefig(tmp)
        plt.close(fig)
        os.replace(tmp, target)
        written.append(target)
    return written
