"""What drives the structure: support motion Omega(t) and forces F(t) with their spatial shapes.

The descriptions (BaseMotion, PointForce, RandomForce, NoExcitation) are plain values: what a scene
or a Python script asks for. The full-order model turns one into its time functions (Harmonic,
RandomProcess) and, for forces, a load at one DOF or a load vector. In relative coordinates
(paper Eqs. 26-27) support motion loads the structure with -M r Omega''(t) and the laws act on the
total displacement u + r Omega(t).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np


@dataclass(frozen=True)
class Harmonic:
    """a sin(2 pi f t + phase) and its derivatives. With phase 0, Omega(0) = 0: a run starts with the
    support at rest. A stepped sine continues the phase of the previous step (sweep.py)."""

    amplitude: float = 0.0
    frequency_hz: float = 0.0
    phase: float = 0.0

    def value(self, t):
        return self.amplitude * np.sin(2 * np.pi * self.frequency_hz * t + self.phase)

    def rate(self, t):
        w = 2 * np.pi * self.frequency_hz
        return self.amplitude * w * np.cos(w * t + self.phase)

    def acceleration(self, t):
        w = 2 * np.pi * self.frequency_hz
        return -self.amplitude * w * w * np.sin(w * t + self.phase)


class RandomProcess:
    """Band-limited random history with a flat one-sided PSD S over [f_low, f_high] (spectral
    representation, Shinozuka): sum_k sqrt(2 S df) cos(2 pi f_k t + phi_k), f_k at the centres of
    `components` equal bins, phi_k uniform from `seed`. Its variance is exactly S (f_high - f_low);
    it is smooth, so adaptive integrators handle it, and the same seed gives the same history."""

    def __init__(self, psd: float, band, seed: int, components: int = 256):
        f_low, f_high = band
        df = (f_high - f_low) / components
        self.frequency = f_low + (np.arange(components) + 0.5) * df
        self.amplitude = np.full(components, np.sqrt(2 * psd * df))
        self.phase = np.random.default_rng(seed).uniform(0, 2 * np.pi, components)
        self.omega = 2 * np.pi * self.frequency

    def value(self, t):
        t = np.asarray(t, dtype=float)
        return np.cos(np.multiply.outer(t, self.omega) + self.phase) @ self.amplitude


@dataclass(frozen=True)
class NoExcitation:
    """Free vibration from the initial state."""

    kind = "none"


@dataclass(frozen=True)
class BaseMotion:
    """The transverse support at `end` ("left" or "right" of a beam; the influence vector of a
    matrix model) moves as amplitude sin(2 pi frequency_hz t) (m); on a beam of two planes along
    the unit vector `direction` (dy, dz)."""

    amplitude: float
    frequency_hz: float
    end: str = "left"
    direction: tuple = (1.0, 0.0)
    kind = "base"

    def support(self) -> Harmonic:
        return Harmonic(self.amplitude, self.frequency_hz)


@dataclass(frozen=True)
class PointForce:
    """amplitude sin(2 pi frequency_hz t) (N) at x (m, a beam) or at DOF `dof` (a matrix model); on a
    beam of two planes along the unit vector `direction` (dy, dz)."""

    amplitude: float
    frequency_hz: float
    x: Optional[float] = None
    dof: Optional[int] = None
    direction: tuple = (1.0, 0.0)
    kind = "force"

    def history(self) -> Harmonic:
        return Harmonic(self.amplitude, self.frequency_hz)


@dataclass(frozen=True)
class RandomForce:
    """A distributed force per unit length on [span[0], span[1]] of a beam, fully correlated along
    the span: a flat one-sided PSD psd ((N/m)^2/Hz) over band = (f_low, f_high) Hz, from seed; on a
    beam of two planes along the unit vector `direction` (dy, dz)."""

    psd: float
    band: tuple
    seed: int = 1
    components: int = 256
    span: tuple = field(default=())
    direction: tuple = (1.0, 0.0)
    kind = "random"

    def history(self) -> RandomProcess:
        return RandomProcess(self.psd, self.band, self.seed, self.components)


def time_functions(excitation) -> tuple:
    """(support motion Omega(t), force history F(t)) of an excitation description; a zero Harmonic
    stands for what it does not have."""
    support = excitation.support() if excitation.kind == "base" else Harmonic()
    force = excitation.history() if excitation.kind in ("force", "random") else Harmonic()
    return support, force
