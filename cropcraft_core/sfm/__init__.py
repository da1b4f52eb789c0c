"""Photos to poses: image ingest (``ingest_images``) and structure from motion / pose import."""

from cropcraft_core.sfm.frame import GravityFrame, level_poses
from cropcraft_core.sfm.ingest import IngestedImage, IngestManifest, ingest_images
from cropcraft_core.sfm.poses import (
    Poses,
    SfmError,
    SfmResult,
    export_colmap_text,
    export_transforms_json,
    import_colmap,
    import_transforms_json,
    run_sfm,
    umeyama,
)

__all__ = [
    "GravityFrame",
    "IngestManifest",
    "IngestedImage",
    "Poses",
    "SfmError",
    "SfmResult",
    "export_colmap_text",
    "export_transforms_json",
    "import_colmap",
    "import_transforms_json",
    "ingest_images",
    "level_poses",
    "run_sfm",
    "umeyama",
]
