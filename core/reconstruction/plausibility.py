"""When a fit is implausible: the one policy on the numbers of ``FitResult.plausibility()``.

Used by the GUI (a red read-out, exports need an explicit yes) and by the headless ``fit`` and
``segment`` commands (one warning line each, and ``warnings`` in ``--json``). The thresholds
are relative to the model's size (its RMS radius) where a fixed number of millimetres would
not fit both a subthalamic nucleus and a thalamus; they flag what a clinician would not accept
without looking: points far from the surface, factors beyond 3 prior SD, a pose far from the
model's placement (the pose prior cannot reach that far: place the model first).
"""

from __future__ import annotations

PLAUSIBLE_RESIDUAL = (3.0, 0.2)           # mm, and fraction of the model size (the larger)
PLAUSIBLE_COEF_SD = 3.0                   # |coefficient| in prior SD
PLAUSIBLE_SHIFT = (10.0, 1.0)             # mm, and model sizes (the larger), from the placement
PLAUSIBLE_ROTATION_DEG = 20.0
PLAUSIBLE_SCALE = (0.75, 1.33)


def plausibility_warnings(p: dict) -> tuple[str, ...]:
    """Why a fit with plausibility numbers ``p`` (``FitResult.plausibility()``) is doubtful."""
    size = p.get("model_size_mm", float("nan"))
    size = size if size == size and size > 0 else 0.0
    out = []
    limit = max(PLAUSIBLE_RESIDUAL[0], PLAUSIBLE_RESIDUAL[1] * size)
    if p.get("residual_mm", 0.0) > limit:
        out.append(f"points {p['residual_mm']:.1f} mm from the surface on average "
                   f"(more than {limit:.1f} mm)")
    if p.get("max_abs_coef_sd", 0.0) > PLAUSIBLE_COEF_SD:
        out.append(f"{p.get('n_coef_beyond_3sd', 1)} shape factor(s) beyond ±3 SD "
                   f"(up to {p['max_abs_coef_sd']:.1f} SD)")
    limit = max(PLAUSIBLE_SHIFT[0], PLAUSIBLE_SHIFT[1] * size)
    if p.get("placement_shift_mm", 0.0) > limit:
        out.append(f"moved {p['placement_shift_mm']:.0f} mm from where it was placed")
    if p.get("placement_rotation_deg", 0.0) > PLAUSIBLE_ROTATION_DEG:
        out.append(f"turned {p['placement_rotation_deg']:.0f}° from its placement")
    scale = p.get("placement_scale_ratio", 1.0)
    if not PLAUSIBLE_SCALE[0] <= scale <= PLAUSIBLE_SCALE[1]:
        out.append(f"scaled by {scale:.2f} from its placement")
    return tuple(out)
