"""Photos to poses: image ingest (``ingest_images``) and structure from motion / pose import."""

from cropcraft_core.sfm.frame import GravityFrame, level_poses
from cropcraft_core.sfm.ingest import IngestedImage, IngestManifest, ingest_images
from cropcraft_core.sfm.poses import (
    ImportedPoses,
    Poses,
    SfmError,
    SfmResult,
    export_colmap_text,
    export_transforms_json,
    import_colmap,
    import_poses,
    import_transforms_json,
    pinhole_photos,
    run_sfm,
    umeyama,
)

__all__ = [
    "GravityFrame",
    "ImportedPoses",
    "IngestManifest",
    "IngestedImage",
    "Poses",
    "SfmError",
    "SfmResult",
    "export_colmap_text",
    "export_transforms_json",
    "import_colmap",
    "import_poses",
    "import_transforms_json",
    "ingest_images",
    "level_poses",
    "pinhole_photos",
    "run_sfm",
    "umeyama",
]
