"""The figures eyeserver is measured by: the paper's value and our goal (docs/design.md §6), in
one place for the command line, the benches and the documentation."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Figure:
    """One figure of docs/design.md §6: what it is, its unit, the paper's value and our goal."""

    label: str
    unit: str
    paper: str
    goal: float


FIGURES: dict[str, Figure] = {
    "reprojection_px": Figure("reprojection error, median", "px", "0.88 (IQR 1.44)", 0.15),
    "p2h_residual_mm": Figure("phase-to-height residual, median", "mm", "0.12 (IQR 0.15)", 0.03),
    "fiducial_error_mm": Figure("3-D at fiducials vs triangulation, median", "mm",
                                "0.58 (IQR 0.70)", 0.15),
    "icp_rmse_4view_mm": Figure("ICP RMSE vs exact surface, 4 views, median", "mm", "0.61",
                                0.15),
    "icp_rmse_2view_mm": Figure("ICP RMSE vs exact surface, 2 views, median", "mm", "0.59",
                                0.15),
    "surface_median_4view_mm": Figure("distance to exact surface, 4 views, median", "mm",
                                      "0.58 (at fiducials)", 0.15),
    "surface_median_2view_mm": Figure("distance to exact surface, 2 views, median", "mm",
                                      "0.58 (at fiducials)", 0.15),
    "surface_rmse_4view_mm": Figure("RMSE to exact surface, 4 views, median", "mm", "—", 0.15),
    "surface_rmse_2view_mm": Figure("RMSE to exact surface, 2 views, median", "mm", "—", 0.15),
    "seam_error_mm": Figure("error at the seam between units", "mm", "1.0–1.5", 0.3),
    "eye_model_distance_mm": Figure("eye (phantom) surface vs its model, median", "mm",
                                    "0.43 (clinical)", 0.10),
    "static_noise_mm": Figure("repeatability of a static surface", "mm", "not reported", 0.03),
    "ftm_phase_error_rad": Figure("single-shot phase vs 4-step phase, median", "rad",
                                  "not reported", 0.02),
}
"""By the JSON key the benches report them under (docs/design.md §8 fixes the first of them)."""
