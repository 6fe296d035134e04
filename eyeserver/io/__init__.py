"""Readers and writers of eyeserver's on-disk formats (FORMATS.md): rig files, capture bundles
and PLY point clouds. Nothing else in eyeserver reads or writes these files.

Readers raise :class:`eyeserver.errors.FormatError` naming the file and the field; writers
raise ``ValueError`` for arguments that would make an invalid file, and write atomically.
"""

from eyeserver.io.atomic import (
    atomic_write_bytes,
    atomic_write_text,
    fsync_dir,
    makedirs_synced,
    write_synced,
)
from eyeserver.io.bundle import (
    BIT_DEPTHS,
    BUNDLE_FILE,
    BUNDLE_FORMAT,
    BUNDLE_KINDS,
    Bundle,
    BundleFrame,
    BundleFrameData,
    BundleKind,
    ChessboardSpec,
    bundle_hash,
    read_bundle,
    write_bundle,
    write_bundle_zip,
)
from eyeserver.io.ply import PointCloud, read_ply, write_ply
from eyeserver.io.rig_file import (
    RIG_FORMAT,
    CameraSpec,
    ProjectorSpec,
    RigSpec,
    UnitSpec,
    check_rig,
    read_rig,
    rig_from_dict,
    write_rig,
)

__all__ = [
    "BIT_DEPTHS",
    "BUNDLE_FILE",
    "BUNDLE_FORMAT",
    "BUNDLE_KINDS",
    "RIG_FORMAT",
    "Bundle",
    "BundleFrame",
    "BundleFrameData",
    "BundleKind",
    "CameraSpec",
    "ChessboardSpec",
    "PointCloud",
    "ProjectorSpec",
    "RigSpec",
    "UnitSpec",
    "atomic_write_bytes",
    "atomic_write_text",
    "bundle_hash",
    "check_rig",
    "fsync_dir",
    "makedirs_synced",
    "read_bundle",
    "read_ply",
    "read_rig",
    "rig_from_dict",
    "write_bundle",
    "write_bundle_zip",
    "write_ply",
    "write_rig",
    "write_synced",
]
