"""Types of echoloc.localise's public names; lazy_loader reads its imports to load each on first use."""

from .backprojection import (
    BackprojectionOptions,
    Backprojector,
    Grid,
    backproject_frame,
    frame_image,
    prepare_backprojection,
    run_backprojection,
)
from .design import DesignStudy, design_record, design_study
from .evaluation import Evaluation, evaluate
from .locate import (
    FrameObjects,
    LocatedObject,
    LocateOptions,
    associate,
    paired_closed_form,
    solve_positions,
)
from .uncertainty import (
    ErrorMap,
    PositionErrors,
    SpacingRecommendation,
    SpacingStudy,
    UncertaintyArea,
    error_map,
    position_errors,
    recommended_spacing,
    spacing_study,
    uncertainty_area,
)

__all__ = [
    "BackprojectionOptions",
    "Backprojector",
    "DesignStudy",
    "ErrorMap",
    "Evaluation",
    "FrameObjects",
    "Grid",
    "LocateOptions",
    "LocatedObject",
    "PositionErrors",
    "SpacingRecommendation",
    "SpacingStudy",
    "UncertaintyArea",
    "associate",
    "backproject_frame",
    "design_record",
    "design_study",
    "error_map",
    "evaluate",
    "frame_image",
    "paired_closed_form",
    "position_errors",
    "prepare_backprojection",
    "recommended_spacing",
    "run_backprojection",
    "solve_positions",
    "spacing_study",
    "uncertainty_area",
]
