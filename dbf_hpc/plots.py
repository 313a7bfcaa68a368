"""Figures (PNG, matplotlib with the Agg backend) of a run, a sweep, and the stiffness sweep of Fig. 2.
Called on one rank; each figure is written under a temporary name and renamed when complete."""
from __future__ import annotations

import json
import os

import numpy as np

from . import layout
from .errors import InputError, replacing
from .schema import unit_of


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def is_dbf_png(path: str) -> bool:
    """Whether `path` is a PNG dbf-hpc drew (its Software text chunk): a plot replaces only those."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    return head.startswith(b"\x89PNG") and b"Software\x00dbf-hpc" in head


def _save(fig, target: str, written: list, layout_done: bool = False) -> None:
    plt = _pyplot()
    if os.path.exists(target) and not is_dbf_png(target):
        plt.close(fig)
        raise InputError(f"{target!r} exists and is not a dbf-hpc plot: remove it or draw into another directory")
    if not layout_done:
        fig.tight_layout()
    try:
        with replacing(target, ".png") as tmp:
            fig.savefig(tmp, metadata={"Software": "dbf-hpc"})
    finally:
        plt.close(fig)
    written.append(target)


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
    _save(fig, path, [])


def parse_window(text: str | None):
    """'T0:T1' (s, either end may be empty) -> (t0, t1) or None; an InputError unless t0 < t1."""
    from .errors import InputError

    if not text:
        return None
    start, colon, end = text.partition(":")
    if not colon:   # "5" alone read as "from 5 s on" (new-user pass): say which end is meant
        try:
            example = f"{float(text):g}"
        except ValueError:   # not a time at all: an example built on it would read "a: (from a s)"
            raise InputError(f"--window {text!r}: give T0:T1 in seconds, e.g. 9: (from 9 s), :1 (to 1 s) "
                             "or 0.5:2") from None
        raise InputError(f"--window {text!r}: give T0:T1 in seconds, e.g. {example}: (from {example} s) "
                         f"or :{example} (to it)")
    try:
        window = (float(start) if start else -np.inf, float(end) if end else np.inf)
    except ValueError:
        window = (np.nan, np.nan)
    if np.isnan(window).any() or not window[0] < window[1]:
        raise InputError(f"--window {text!r}: give T0:T1 in seconds with T0 < T1 (either may be left out)")
    return window


def _panels(count: int, width: float = 8.0, height: float = 2.2):
    """A figure with `count` stacked panels (two columns beyond eight)."""
    plt = _pyplot()
    columns = 1 if count <= 8 else 2
    rows = int(np.ceil(count / columns))
    fig, axes = plt.subplots(rows, columns, figsize=(width * columns ** 0.5, 1.0 + height * rows), dpi=110,
                             squeeze=False, sharex=True)
    for ax in axes.ravel()[count:]:
        ax.set_visible(False)
    return fig, axes.ravel()[:count]


def _where(x: float) -> str:
    return f"x = {x:g} m"


def plot_run(path: str, folder: str, window=None) -> list:
    """The paper's figures for one run's output, as PNGs in `folder`; returns the files written.

    time_histories.png: w at each constraint with its clearance (Figs. 4, 7); phase.png: phase
    diagrams (Figs. 5, 8, 12); forces.png: the peak force per sample interval (Fig. 10); probes.png:
    w at each probe; snapshots.png: the field at the snapshot times with the constraints and their
    deadbands (Figs. 6, 9, 11, 13). On a beam of two planes also orbits.png: each support's path z
    against y inside its gap (the clearance circle of a round hole, the two lines of flat bars).
    `window` (t0, t1) limits every figure to its samples and snapshots (none in it: no snapshots
    figure); the files then carry the window's sample span (time_histories_9-10s.png), so that they
    never replace the whole run's figures.
    """
    import h5py

    written = []
    with h5py.File(path, "r") as f:
        t = f[layout.TIME][:]
        keep = (t >= window[0]) & (t <= window[1]) if window else np.ones(t.size, dtype=bool)
        positions = f[layout.CONSTRAINT_POSITION][:]
        series = {name: f[name][:][keep] for name in (layout.CONSTRAINT_DISPLACEMENT, layout.CONSTRAINT_VELOCITY,
                                                       layout.CONSTRAINT_FORCE_PEAK, layout.PROBE_DISPLACEMENT)}
        gaps = (f[layout.CONSTRAINT_CLEARANCE_MINUS][:], f[layout.CONSTRAINT_CLEARANCE_PLUS][:])
        span = f"t = {t[keep][0]:g} ... {t[keep][-1]:g} s" if keep.any() else "no samples"
        tag = f"_{t[keep][0]:g}-{t[keep][-1]:g}s" if window and keep.any() else ""

        def name(stem: str) -> str:
            return os.path.join(folder, f"{stem}{tag}.png")

        if positions.size:
            _constraint_figures(name, t[keep], positions, series, gaps, span, written)
            if series[layout.CONSTRAINT_DISPLACEMENT].ndim == 3:
                _orbit_figure(name, positions, series[layout.CONSTRAINT_DISPLACEMENT], _laws(f), span, written)
        probes = f[layout.PROBE_POSITION][:] if layout.PROBE_POSITION in f else np.zeros(0)
        if probes.size:
            fig, axes = _panels(probes.size)
            for p, ax in enumerate(axes):
                ax.plot(t[keep], series[layout.PROBE_DISPLACEMENT][:, p] * 1e3, lw=0.8, color="C4")
                ax.set_ylabel(f"w({probes[p]:g}) [mm]")
                ax.grid(alpha=0.3)
            axes[-1].set_xlabel("time t [s]")
            fig.suptitle(f"Displacement at the probes ({span})")
            _save(fig, name("probes"), written)
        ts = f[layout.SNAPSHOT_TIME][:]
        chosen = np.flatnonzero((ts >= window[0]) & (ts <= window[1]) if window else np.ones(ts.size, dtype=bool))
        if chosen.size:
            _snapshot_figure(name("snapshots"), f, chosen, positions, gaps, written)
    return written


def _constraint_figures(name, t, positions, series, gaps, span, written) -> None:
    z, v = series[layout.CONSTRAINT_DISPLACEMENT], series[layout.CONSTRAINT_VELOCITY]
    force = series[layout.CONSTRAINT_FORCE_PEAK]
    fig, axes = _panels(positions.size)
    for j, ax in enumerate(axes):
        for (values, label), color in zip(_components(z, j), ("C0", "C1")):
            ax.plot(t, values * 1e3, lw=0.8, color=color, label=label)
        for level in (-gaps[0][j], gaps[1][j]):
            ax.axhline(level * 1e3, color="C3", ls="--", lw=0.8)
        ax.set_ylabel(f"w [mm]\n{_where(positions[j])}")
        _legend(ax, z)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time t [s]")
    fig.suptitle(f"Displacement at the constraints (dashed: clearance; {span})")
    _save(fig, name("time_histories"), written)

    plt = _pyplot()
    columns = min(positions.size, 3)
    rows = int(np.ceil(positions.size / columns))
    fig, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.6 * rows), dpi=110, squeeze=False)
    for ax in axes.ravel()[positions.size:]:
        ax.set_visible(False)
    for j, ax in enumerate(axes.ravel()[:positions.size]):
        for (w, label), (dw, _), color in zip(_components(z, j), _components(v, j), ("C0", "C1")):
            ax.plot(w * 1e3, dw, lw=0.6, color=color, label=label)
        _legend(ax, z)
        ax.set_xlabel("w [mm]")
        ax.set_ylabel("dw/dt [m/s]")
        ax.set_title(_where(positions[j]), fontsize=9)
        ax.grid(alpha=0.3)
    fig.suptitle(f"Phase diagrams at the constraints ({span})")
    _save(fig, name("phase"), written)

    fig, axes = _panels(positions.size)
    for j, ax in enumerate(axes):
        for (values, label), color in zip(_components(force, j), ("C2", "C1")):
            ax.plot(t, values, lw=0.8, color=color, label=label)
        _legend(ax, force)
        ax.set_ylabel(f"force [N]\n{_where(positions[j])}")
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time t [s]")
    fig.suptitle(f"Constraint force, the peak over each sample interval ({span})")
    _save(fig, name("forces"), written)


def _components(a: np.ndarray, j: int) -> list:
    """(values, label) of constraint j's samples: one unlabelled series, or y and z on a beam of two
    planes (the samples' last axis)."""
    return [(a[:, j], None)] if a.ndim == 2 else [(a[:, j, 0], "y"), (a[:, j, 1], "z")]


def _legend(ax, a: np.ndarray) -> None:
    if a.ndim == 3:   # y and z: say which is which
        ax.legend(fontsize=7, loc="upper right")


def _laws(f) -> list:
    """Each constraint's law (a dict: kind, clearance, angle) from the run's effective scene."""
    try:
        return [c["law"] for c in json.loads(f.attrs["scene_effective"])["constraint"]]
    except (KeyError, ValueError, TypeError):
        return []


def _orbit_figure(name, positions, u, laws, span, written) -> None:
    """orbits.png: z against y (mm) at each support of two directions, with its gap drawn."""
    plt = _pyplot()
    n = positions.size
    columns = min(n, 4)
    rows = int(np.ceil(n / columns))
    fig, axes = plt.subplots(rows, columns, figsize=(3.4 * columns, 3.4 * rows), dpi=110, squeeze=False)
    for ax in axes.ravel()[n:]:
        ax.set_visible(False)
    turn = np.linspace(0, 2 * np.pi, 241)
    for j, ax in enumerate(axes.ravel()[:n]):
        law = laws[j] if j < len(laws) else {}
        c = float(law.get("clearance", 0.0)) * 1e3
        reach = max(1.3 * c, 1.1 * float(np.abs(u[:, j]).max(initial=0.0)) * 1e3, 1e-9)
        if law.get("kind") == "flat_bar":   # the flats: u.e = +-c, e at `angle` from y
            a = np.radians(float(law.get("angle", 0.0)))
            e, s = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
            for side in (-1, 1):
                ends = side * c * e[:, None] + s[:, None] * np.array([-2 * reach, 2 * reach])
                ax.plot(ends[0], ends[1], color="C3", lw=1.2)
            gap = f"flats at {float(law.get('angle', 0.0)):g} deg, gap {c:.3g} mm"
        else:
            ax.plot(c * np.cos(turn), c * np.sin(turn), color="C3", lw=1.2)
            gap = f"clearance {c:.3g} mm"
        ax.plot(u[:, j, 0] * 1e3, u[:, j, 1] * 1e3, lw=0.5, color="C0")
        ax.set_xlim(-reach, reach)
        ax.set_ylim(-reach, reach)
        ax.set_aspect("equal")
        ax.set_xlabel("y [mm]")
        ax.set_ylabel("z [mm]")
        ax.set_title(f"{_where(positions[j])}: {gap}", fontsize=8)
        ax.grid(alpha=0.3)
    fig.suptitle(f"Orbits of the tube in its supports ({span})")
    _save(fig, name("orbits"), written)


def _snapshot_figure(target, f, chosen, positions, gaps, written) -> None:
    """The field at the snapshots `chosen` (indices) into `target`."""
    plt = _pyplot()
    xs, ts = f[layout.SNAPSHOT_X][:], f[layout.SNAPSHOT_TIME][:][chosen]
    kind = f.attrs.get("field_kind", "beam")
    beam = kind == "beam"
    if kind == "nodes":      # a model with a node map: |u| at each node along x (ParaView shows it in 3-D)
        xs = f["snapshots/points"][:, 0]
        ws = np.array([np.linalg.norm(f[f"snapshots/displacement/{i:06d}"][:], axis=1) for i in chosen])
        order = np.argsort(xs, kind="stable")
        xs, ws = xs[order], ws[:, order]
    else:
        ws = f[layout.SNAPSHOT_W][chosen[0]:chosen[-1] + 1][chosen - chosen[0]]
    fig, ax = plt.subplots(figsize=(7.5, 4.2), dpi=120)
    colors = plt.cm.viridis(np.linspace(0, 1, ws.shape[0]))
    for w, c in zip(ws, colors):
        ax.plot(xs, w * 1e3, ".-" if kind == "nodes" else "-", ms=2, color=c, lw=0.7)
    for j, x in enumerate(positions if beam else ()):
        ax.axvline(x, color="k", lw=0.6, alpha=0.6)
        ax.plot([x, x], [-gaps[0][j] * 1e3, gaps[1][j] * 1e3], color="C3", lw=3, alpha=0.7)
    ax.set_xlabel("DOF" if kind == "dofs" else "position x [m]")
    ax.set_ylabel({"beam": "total displacement w [mm]", "nodes": "|u| at the nodes [mm]"}.get(
        kind, "total displacement [mm or mrad]"))
    ax.set_title(f"{ws.shape[0]} snapshots, t = {ts[0]:g} ... {ts[-1]:g} s"
                 + (" (vertical: constraints, red: deadband)" if beam else ""))
    ax.grid(alpha=0.3)
    sm = plt.cm.ScalarMappable(cmap="viridis", norm=plt.Normalize(ts[0], ts[-1]))
    fig.colorbar(sm, ax=ax, label="t [s]")
    _save(fig, target, written)


def _read_sweep(f) -> dict:
    ok = np.array([s in (b"ok", "ok") for s in f["cases/status"][:]])
    columns = {}
    for name in json.loads(f.attrs["sweep"])["parameters"]:
        raw = f[f"cases/parameters/{name}"][:]
        columns[name] = raw if raw.dtype.kind == "f" else np.array([json.loads(v) for v in raw], dtype=object)
    stats = {name: f[f"cases/stats/{name}"][:] for name in
             ("displacement_peak", "impact_rate", "contact_fraction", "force_peak", "work_rate", "work_rate_ci95")
             if f"cases/stats/{name}" in f}
    return {"ok": ok, "columns": columns, "stats": stats, "probe_peak": f["cases/probe_peak"][:]}


PANELS = (("displacement_peak", "peak |w| [mm]", 1e3), ("impact_rate", "impacts per second [1/s]", 1),
          ("contact_fraction", "fraction of time in contact", 1), ("force_peak", "peak force [N]", 1))
# supports of two directions: the normal work rate in place of the contact fraction
PANELS_2D = PANELS[:2] + (("work_rate", "normal work rate [mW]\n(bars: 95 % interval)", 1e3),) + PANELS[3:]


def plot_sweep(path: str, folder: str, window=None) -> list:
    """Statistics of a sweep summary against each numeric parameter that varies, one line per
    combination of the other varying parameters (and sweep direction), each line its own colour:
    peak displacement at each constraint and probe (a frequency response when the parameter is the
    excitation frequency), impact rate, contact fraction (supports of two directions: the normal work
    rate, with its 95 % confidence intervals as error bars) and peak force. Failed cases are marked
    with a red cross on the axis. (`window` is for runs; a sweep has no time axis: `dbf-hpc plot`
    refuses --window for a summary.)"""
    import h5py

    with h5py.File(path, "r") as f:
        data = _read_sweep(f)
    columns, written = data["columns"], []
    present = lambda v: [x for x in v if x is not None and not (isinstance(x, float) and np.isnan(x))]  # noqa: E731
    varying = [n for n, v in columns.items() if len({repr(x) for x in present(v)}) > 1]
    for name in varying:
        if columns[name].dtype.kind == "f":
            _sweep_figure(folder, name, [n for n in varying if n != name], data, written)
    return written


UNSET = "not set"   # a sweep figure's label for a parameter a listed case leaves at the scene's value


def _sweep_figure(folder, name, others, data, written) -> None:
    plt = _pyplot()
    columns, ok = data["columns"], data["ok"]
    x = columns[name]
    # a listed case that does not set another parameter has NaN there: one key for all of them (NaN
    # never equals itself, so such a case matched no line and was left out of the figure: red team)
    keys = [tuple(UNSET if isinstance(v, float) and np.isnan(v) else v for v in (columns[n][i] for n in others))
            for i in range(x.size)]
    series = list(dict.fromkeys(keys))
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5), dpi=110, sharex=True)
    colour = iter(plt.cm.tab20(np.linspace(0, 1, 20)))
    colours = {}
    for ax, (stat, label, scale) in zip(axes.ravel(), PANELS_2D if "work_rate" in data["stats"] else PANELS):
        for key in series:
            _sweep_lines(ax, stat, scale, key, keys, x, others, data, colours, colour)
        failed = x[~ok & np.isfinite(x)]
        if failed.size:
            ax.plot(failed, np.zeros(failed.size), "x", color="red", ms=8, mew=2, label="failed case", clip_on=False)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    unit = unit_of(name)
    for ax in axes[1]:
        ax.set_xlabel(f"{name} [{unit}]" if unit else name)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    unique = dict(zip(labels, handles))
    # as many columns as the longest label lets fit across the figure (~160 characters at this size)
    ncol = max(1, min(4, len(unique), 160 // (max((len(k) for k in unique), default=1) + 8)))
    rows = int(np.ceil(len(unique) / ncol))
    fig.legend(unique.values(), unique.keys(), loc="lower center", ncol=ncol, fontsize=7)
    fig.suptitle(f"Sweep over {name}: {int(ok.sum())} of {ok.size} cases ran"
                 + (f", {int((~ok).sum())} failed (red crosses)" if (~ok).any() else ""))
    fig.tight_layout(rect=(0, 0.035 * rows + 0.01, 1, 1))
    _save(fig, os.path.join(folder, f"sweep_{name.replace('.', '_')}.png"), written, layout_done=True)


def _sweep_lines(ax, stat, scale, key, keys, x, others, data, colours, colour) -> None:
    """One combination of the other parameters: a line per constraint (or the mean and the worst of
    many), and the probes on the displacement panel; each line keeps its colour across panels."""
    sel = np.array([k == key for k in keys]) & data["ok"] & np.isfinite(x)
    if not sel.any():
        return
    order = np.flatnonzero(sel)[np.argsort(x[sel], kind="stable")]
    tag = ", ".join(f"{n.split('.')[-1]} {v}" for n, v in zip(others, key))
    tag = f" ({tag})" if tag else ""
    style = "v--" if "down" in key else "o-"
    table = data["stats"][stat][order] * scale
    # the 95 % confidence half-widths where the summary has them (the work rate): error bars on each
    # constraint's line and on the worst one's (a wear study reads the rate with its interval)
    ci = data["stats"].get(f"{stat}_ci95")
    ci = None if ci is None else ci[order] * scale
    if table.shape[1] > 4:
        worst = np.nanargmax(np.where(np.isnan(table), -np.inf, table), axis=1)
        lines = [("mean over constraints", np.nanmean(table, axis=1), None),
                 ("worst constraint", table[np.arange(len(order)), worst],
                  None if ci is None else ci[np.arange(len(order)), worst])]
    else:
        lines = [(f"constraint {j + 1}", table[:, j], None if ci is None else ci[:, j]) for j in range(table.shape[1])]
    if stat == "displacement_peak":
        lines += [(f"probe {p + 1}", data["probe_peak"][order, p] * 1e3, None)
                  for p in range(data["probe_peak"].shape[1])]
    for label, values, error in lines:
        full = f"{label}{tag}"
        if full not in colours:
            colours[full] = next(colour, "k")
        if error is None:
            ax.plot(x[order], values, style, ms=3, lw=1, color=colours[full], label=full)
        else:
            ax.errorbar(x[order], values, yerr=error, fmt=style, ms=3, lw=1, capsize=2, color=colours[full],
                        label=full)
