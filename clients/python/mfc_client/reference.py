"""Reference pieces: a channel's reference is the sum of its pieces.

Times are seconds on the plant's clock, relative to the reference's ``start_time``; values
are in the plant's output units. The controller evaluates the pieces itself (with exact
derivatives, which the intelligent controllers use as feed-forward), so a reference is a
description, not a stream of set-points.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from ._pb import pb


def constant(value: float) -> pb.Piece:
    """``value`` at all times."""
    return pb.Piece(constant=pb.Constant(value=value))


def ramp(start: float, end: float, slope: float) -> pb.Piece:
    """0 before ``start``, rising at ``slope`` per second until ``end``, then held."""
    return pb.Piece(ramp=pb.Ramp(start=start, end=end, slope=slope))


def smooth_step(start: float, duration: float, height: float) -> pb.Piece:
    """0 before ``start``, ``height`` after ``start + duration`` (duration > 0), joined by a
    quintic that is continuous up to the second derivative."""
    return pb.Piece(smooth_step=pb.SmoothStep(start=start, duration=duration, height=height))


def sine(
    amplitude: float,
    period: float,
    *,
    phase: float = 0.0,
    start: float = 0.0,
    end: float | None = None,
    fade: float = 0.0,
) -> pb.Piece:
    """``amplitude * sin(2 pi (t - start) / period + phase)`` from ``start`` to ``end`` (never
    ends if None), faded in and out over ``fade`` seconds."""
    s = pb.Sine(amplitude=amplitude, period=period, phase=phase, start=start, fade=fade)
    if end is not None:
        s.end = end
    return pb.Piece(sine=s)


def reference(channels: Sequence[Sequence[pb.Piece]], start_time: float = 0.0) -> pb.Reference:
    """A whole reference: one list of pieces per channel, in the device's channel order,
    evaluated at ``plant_time - start_time``."""
    return pb.Reference(
        channels=[pb.ChannelReference(pieces=list(p)) for p in channels],
        start_time=start_time,
    )


def _smoothstep(t: float, start: float, duration: float) -> float:
    s = (t - start) / duration
    if s <= 0.0:
        return 0.0
    if s >= 1.0:
        return 1.0
    return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)


def piece_value(p: pb.Piece, t: float) -> float:
    """The value of one piece at ``t`` (seconds after the reference's start), as the
    controller computes it (``mfc/src/trajectory.rs``)."""
    shape = p.WhichOneof("shape")
    if shape == "constant":
        return p.constant.value
    if shape == "ramp":
        r = p.ramp
        return r.slope * (min(max(t, r.start), r.end) - r.start)
    if shape == "smooth_step":
        s = p.smooth_step
        return s.height * _smoothstep(t, s.start, s.duration)
    if shape == "sine":
        w = p.sine
        end = w.end if w.HasField("end") else math.inf
        if t < w.start or t > end:
            return 0.0
        v = w.amplitude * math.sin(2.0 * math.pi / w.period * (t - w.start) + w.phase)
        if w.fade > 0.0:
            v *= _smoothstep(t, w.start, w.fade)
            if math.isfinite(end):
                v *= _smoothstep(-t, -end, w.fade)
        return v
    return 0.0


def evaluate(ref: pb.Reference, t: float) -> list[float]:
    """Each channel's reference value at plant time ``t``: what the controller aims at, so
    that a plant can measure its own tracking error."""
    return [sum(piece_value(p, t - ref.start_time) for p in c.pieces) for c in ref.channels]
