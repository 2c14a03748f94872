"""Unit conversions at the transport edge: encoder counts and per-mille effort, defined once.

Inside drivectl everything is SI (m, m/s, N or V). A CiA 402 drive speaks position actual 0x6064
in counts, velocity actual 0x606C in counts/s and torque 0x6071/0x6077 in per-mille of rated
torque 0x6076. The drive and the emulator both use these functions, so a value survives the round
trip bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

#: paper 004's encoders: 76.29 nm per count after the angle-to-distance conversion
DEFAULT_RESOLUTION_M = 76.29e-9


@dataclass(frozen=True, slots=True)
class Encoder:
    """Position scaling of one axis: metres per count."""

    resolution: float = DEFAULT_RESOLUTION_M

    def __post_init__(self) -> None:
        if not self.resolution > 0:
            raise ValueError(f"encoder resolution: must be > 0 m per count, got {self.resolution!r}")

    def to_counts(self, metres: float) -> int:
        return round(metres / self.resolution)

    def from_counts(self, counts: int) -> float:
        return counts * self.resolution

    def velocity(self, counts: int, counts_before: int, seconds: float) -> float:
        """The velocity between two positions in counts ``seconds`` apart (host-derived, compact mapping)."""
        return (counts - counts_before) * self.resolution / seconds

    def quantise(self, metres: float) -> float:
        """What the encoder reports for a true position: the nearest whole count, in metres."""
        return round(metres / self.resolution) * self.resolution


@dataclass(frozen=True, slots=True)
class EffortScale:
    """Effort scaling of one axis: the effort (N or V) that 1000 per-mille (rated torque) stands for."""

    rated: float

    #: the largest rated effort: 0x6076 holds it in thousandths as UNSIGNED32
    MAX_RATED = 0xFFFF_FFFF / 1000

    def __post_init__(self) -> None:
        if not self.rated > 0:
            raise ValueError(f"effort scale: rated effort must be > 0, got {self.rated!r}")
        if not self.rated <= self.MAX_RATED:
            raise ValueError(f"effort scale: rated effort must be <= {self.MAX_RATED:g} (0x6076 holds it in "
                             f"thousandths, 32 bits), got {self.rated!r}")

    @property
    def rated_thousandths(self) -> int:
        """The value of 0x6076 (rated torque, in thousandths of the effort unit)."""
        return round(self.rated * 1000)

    def to_permille(self, effort: float) -> int:
        """Per mille of rated, clipped to what 0x6071 (INTEGER16) can carry."""
        p = round(effort * 1000.0 / self.rated)
        return -32767 if p < -32767 else 32767 if p > 32767 else p

    def from_permille(self, permille: int) -> float:
        return permille * self.rated / 1000.0
