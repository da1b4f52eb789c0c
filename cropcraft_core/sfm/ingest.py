"""Image ingest: a folder or fsspec URL of photos → checked, normalised images and a manifest.

Every JPEG/PNG file is decoded in full (``Image.load()``), so a corrupt or truncated file fails
here, named, rather than deep inside SfM. EXIF orientation is applied to the pixels (the written
images carry no orientation tag), images are optionally downscaled so that their longer side is at
most ``max_size`` pixels, and exact duplicates are dropped. The camera's focal length, where
EXIF gives it, is kept as ``focal_px`` at the written size (:func:`exif_focal_px`): structure
from motion starts from it rather than from a guess. So is the camera's GPS position, as
``gps`` (latitude, longitude, altitude: :func:`exif_gps`), which can set the poses' metric scale
(:mod:`cropcraft_core.sfm.gps`).

Two hashes per image, both SHA-256:

* ``sha256_file``: of the source file's bytes (provenance: which file was read);
* ``sha256_pixels``: of the decoded, orientation-corrected RGB pixels plus their size. Duplicates
  are decided on this one, so the same photo saved twice (different names or metadata) counts
  once; the first in name order is kept.

``manifest.json`` in the destination lists both hashes, sizes, the source names and the dropped
duplicates and ignored files.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path, PurePosixPath

from PIL import Image, ImageFile, UnidentifiedImageError

from cropcraft_core.errors import InputError, OutputError
from cropcraft_core.store import config_hash

#: Extensions read as photos (case-insensitive).
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png")
#: Extensions of image formats CropCraft recognises but does not read: an error, not ignored
#: (except :data:`COMPANION_EXTENSIONS` beside JPEG/PNG photos).
UNSUPPORTED_EXTENSIONS = (
    ".heic", ".heif", ".tif", ".tiff", ".bmp", ".gif", ".webp", ".dng", ".cr2", ".cr3", ".nef",
    ".arw", ".raw", ".jxl", ".avif",
)  # fmt: skip
#: Formats a camera writes beside its JPEGs rather than instead of them (a drone's RAW+JPEG
#: mode, a multispectral drone's band TIFFs): ignored (and listed) in a folder that holds
#: JPEG/PNG photos, an error in one that holds none. A phone's HEIC is its photos: an error.
COMPANION_EXTENSIONS = (".dng", ".cr2", ".cr3", ".nef", ".arw", ".raw", ".tif", ".tiff")
_FORMATS = {"JPEG", "PNG", "MPO"}  # MPO: multi-picture JPEG some phones write
MANIFEST_NAME = "manifest.json"


@dataclass(frozen=True)
class IngestedImage:
    """One written image. Sizes in pixels; ``scale`` = written / decoded size."""

    name: str
    source: str
    sha256_file: str
    sha256_pixels: str
    width: int
    height: int
    source_width: int
    source_height: int
    exif_orientation: int
    scale: float
    format: str
    focal_px: float | None = None
    """The focal length in pixels of the written image, from the photo's EXIF
    (:func:`exif_focal_px`); None where EXIF does not give it."""
    gps: list[float] | None = None
    """[latitude, longitude (degrees, WGS84), altitude (m)] of the camera from the photo's EXIF
    (:func:`exif_gps`); None where EXIF does not give all three."""


@dataclass(frozen=True)
class IngestManifest:
    """What ``ingest_images`` read and wrote.

    images: written images, in name order.  duplicates: ``{"source", "duplicate_of"}`` records of
    dropped files.  ignored: source files that are not photos (other extensions, hidden files).
    """

    source: str
    dest_dir: str
    max_size: int | None
    images: list[IngestedImage]
    duplicates: list[dict[str, str]] = field(default_factory=list)
    ignored: list[str] = field(default_factory=list)
    in_subfolders: list[str] = field(default_factory=list)
    """Photos in the source's subfolders, which are not read (paths relative to it)."""
    duplicate_key: str = "sha256 of the decoded RGB pixels (after EXIF orientation) and their size"

    @property
    def names(self) -> list[str]:
        return [im.name for im in self.images]

    def __len__(self) -> int:
        return len(self.images)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["n_images"] = len(self.images)
        for im in d["images"]:  # photos without a GPS position: the bytes as before
            if im["gps"] is None:
                del im["gps"]
        if not d["in_subfolders"]:  # a folder without subfolders: the bytes as before
            del d["in_subfolders"]
        return d

    def identity(self) -> str:
        """sha256 of what the written images are, apart from where and how they were read.

        Covers each written image's name, the source name it came from, its pixel hash, sizes,
        orientation, scale and format, and ``max_size``: what a later stage reads (the poses
        map source names to written names). Leaves out the provenance: the source URI, the
        destination folder (a fresh scratch folder in a pipeline), the source files' byte
        hashes (a re-saved photo with new metadata has the same pixels) and the dropped
        duplicates and ignored files. The same photos read again from a copy, with new
        modification times, give the same identity, so nothing keyed on it is recomputed.
        """
        images = [{k: v for k, v in asdict(im).items() if k != "sha256_file"} for im in self.images]
        for im in images:  # photos without one key as before focal lengths (GPS) were read
            for k in ("focal_px", "gps"):
                if im[k] is None:
                    del im[k]
        return config_hash({"max_size": self.max_size, "images": images})

    @classmethod
    def read(cls, path: str | os.PathLike) -> IngestManifest:
        p = Path(path)
        if p.is_dir():
            p = p / MANIFEST_NAME
        try:
            d = json.loads(p.read_text(encoding="utf-8"))
            d.pop("n_images", None)
            d["images"] = [IngestedImage(**im) for im in d["images"]]
            return cls(**d)
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise InputError(f"cannot read the ingest manifest {p}: {e}") from None


#: Characters a written photo's name cannot hold as a store key (``store._check_key``):
#: backslashes and control characters, each written as ``_``.
_UNKEYABLE = re.compile(r"[\\\x00-\x1f\x7f]")


#: Longest stem (UTF-8 bytes) of a written photo's name: a file system holds 255 bytes a name,
#: and the store's temporary sibling adds 38 (a 249-byte name, legal where it came from,
#: failed at storing, blaming the store: session 94's folders audit).
MAX_STEM_BYTES = 160


def _short(stem: str) -> str:
    """``stem``, or where longer than :data:`MAX_STEM_BYTES` its start and a digest of the
    whole (distinct names stay distinct)."""
    raw = stem.encode("utf-8")
    if len(raw) <= MAX_STEM_BYTES:
        return stem
    head = raw[: MAX_STEM_BYTES - 13].decode("utf-8", errors="ignore")
    return f"{head}-{hashlib.sha256(raw).hexdigest()[:12]}"


def _list_source(source: str) -> tuple[object, list[str], str, list[str]]:
    """(filesystem, sorted file paths directly in the source folder, root path, sorted paths
    of its subfolders and links to folders); InputError naming its photos that are links to
    nothing (:func:`check_photo_links`)."""
    import fsspec

    try:
        fs, root = fsspec.core.url_to_fs(source)
    except (ValueError, ImportError) as e:
        raise InputError(f"cannot open image source {source!r}: {e}") from None
    with contextlib.suppress(Exception):
        fs.invalidate_cache(root)  # s3fs keeps a folder's listing for the process's life
    try:
        if not fs.isdir(root):
            what = "is a file, not a folder" if fs.isfile(root) else "does not exist"
            raise InputError(f"image source {source!r} {what}")
        entries = fs.ls(root, detail=True)
    except InputError:
        raise
    except (OSError, PermissionError) as e:
        raise InputError(f"cannot list image source {source!r}: {e}") from None
    files = sorted(e["name"] for e in entries if is_listed_file(fs, e))
    # a link to a folder of photos is a folder (its photos then named as in a subfolder)
    folders = sorted(
        e["name"]
        for e in entries
        if e.get("type") == "directory" or (e.get("islink") and fs.isdir(e["name"]))
    )
    check_photo_links(fs, entries, source)
    return fs, files, root, folders


def check_photo_links(fs, entries: list[dict], where: str) -> None:
    """InputError naming the JPEG/PNG photos among a listing's ``entries`` that are links
    whose target is not there (a git-annex or DVC checkout whose content was never fetched):
    dropped without a word, they read as "no images found" or as fewer photos (session 94's
    folders audit)."""
    broken = sorted(
        str(e["name"]).rsplit("/", 1)[-1]
        for e in entries
        if e.get("islink")
        and str(e["name"]).lower().endswith(IMAGE_EXTENSIONS)
        and not fs.exists(e["name"])
    )
    if broken:
        raise InputError(
            f"{len(broken)} photo(s) in {where} are links whose target is not there: "
            f"{', '.join(broken[:8])}{', ...' if len(broken) > 8 else ''}; a git-annex or DVC "
            "checkout not fetched yet (git annex get, dvc pull)? Fetch them, or remove the links"
        )


def photos_in_subfolders(fs, root: str, folders: list[str], depth: int = 3) -> list[str]:
    """The JPEG/PNG photos (paths relative to ``root``) in the subfolders of a photo folder,
    up to ``depth`` levels down, hidden ones aside: ingest reads the folder itself only (a
    nerfstudio folder's ``images_2/`` holds the same photos at half size), so these are left
    out, and named. [] where they cannot be listed."""
    base = str(root).rstrip("/")
    out = []
    for folder in folders:
        try:
            found = fs.find(folder, maxdepth=depth)
        except Exception:  # unlisted: the photos read are not in doubt
            continue
        for name in found:
            rel = str(name)[len(base) + 1 :]
            if is_visible_photo(rel):
                out.append(rel)
    return sorted(out)


def is_visible_photo(rel: str) -> bool:
    """Whether a relative path names a JPEG/PNG photo, no part of it hidden."""
    return rel.lower().endswith(IMAGE_EXTENSIONS) and not any(
        part.startswith(".") for part in rel.split("/")
    )


def photos_below(source: str | os.PathLike, depth: int = 3) -> list[str]:
    """:func:`photos_in_subfolders` of the folder or fsspec URL ``source`` (subfolders ``depth``
    levels deep); [] where it cannot be listed."""
    try:
        fs, _, root, folders = _list_source(os.fspath(source))
    except Exception:  # a hint's helper: the caller's own error stands
        return []
    return photos_in_subfolders(fs, root, folders, depth)


def is_listed_file(fs, info: dict) -> bool:
    """Whether a listing's entry is a file to read: a file, or a link to one (fsspec lists a
    local symlink as type ``other``, and photos linked into a folder are common: a folder of
    links into a camera dump, a DVC or git-annex checkout)."""
    if info.get("type") == "file":
        return True
    return bool(info.get("islink")) and fs.isfile(info["name"])


def _grey16_to_8(img: Image.Image) -> Image.Image:
    """A 16-bit (or 32-bit integer) greyscale image as 8-bit greyscale, its top 8 bits:
    Pillow's ``convert("RGB")`` clips every value over 255 to white instead of scaling."""
    import numpy as np

    a = np.asarray(img)
    return Image.fromarray((a.astype(np.uint32) >> 8).clip(0, 255).astype(np.uint8), "L")


# EXIF orientation -> the transpose that makes the pixels upright (EXIF 2.32, tag 0x0112).
_UPRIGHT = {
    2: Image.Transpose.FLIP_LEFT_RIGHT,
    3: Image.Transpose.ROTATE_180,
    4: Image.Transpose.FLIP_TOP_BOTTOM,
    5: Image.Transpose.TRANSPOSE,
    6: Image.Transpose.ROTATE_270,
    7: Image.Transpose.TRANSVERSE,
    8: Image.Transpose.ROTATE_90,
}


def _orientation(img: Image.Image, label: str) -> int:
    """The EXIF orientation tag of a decoded image (1 if none). Only that tag is read, so a
    photo whose other EXIF tags are malformed still ingests (the pixels carry no EXIF on);
    EXIF that cannot be parsed at all leaves the orientation unknown: an InputError naming
    the file, since guessing would store the photo sideways. A value outside EXIF's 1-8
    (some software writes 0 or 9) says nothing: the photo is read as stored, as viewers
    show it."""
    try:
        value = int(img.getexif().get(0x0112, 1) or 1)
        return value if 1 <= value <= 8 else 1
    except Exception as e:  # PIL raises struct.error, TypeError, KeyError... on bad EXIF
        raise InputError(
            f"image {label}: its EXIF metadata cannot be parsed ({type(e).__name__}: {e}), so "
            "its orientation is unknown; re-save it without EXIF (e.g. exiftool -all= FILE)"
        ) from None


#: The diagonal of a 36 x 24 mm frame: a 35 mm-equivalent focal length is the focal length
#: that gives the photo's diagonal field of view on it (CIPA DC-008, as phones compute it).
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)
#: EXIF FocalPlaneResolutionUnit -> millimetres (2: inch, 3: cm; 4: mm, 5: um in EXIF 3.0).
_PLANE_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}
#: A focal length outside this many times the photo's longer side is not believed (a
#: placeholder value, a lens adapter's, a digital zoom's crop recorded without its factor).
FOCAL_RANGE = (0.3, 6.0)


def exif_focal_px(img: Image.Image) -> float | None:
    """The focal length in pixels of the decoded photo ``img`` (its stored size; orientation
    does not change it), from its EXIF, or None.

    From ``FocalLengthIn35mmFilm`` (what phones and drones write): f_px = f35 · diagonal_px /
    43.27 mm. Otherwise from ``FocalLength`` (mm) and ``FocalPlaneXResolution`` (pixels per
    unit of the sensor), only where the EXIF pixel dimensions are this photo's (an edited or
    resized photo keeps the camera's resolution). Values that are missing, zero, unreadable
    or outside :data:`FOCAL_RANGE` × the longer side give None: a prior is only worth having
    when it is right, and without one SfM starts from its own guess.
    """
    w, h = img.size
    try:
        sub = img.getexif().get_ifd(0x8769)
        f35 = float(sub.get(0xA405) or 0)
        if f35 > 0:
            f = f35 * math.hypot(w, h) / FULL_FRAME_DIAGONAL_MM
        else:
            f_mm = float(sub.get(0x920A) or 0)
            res = float(sub.get(0xA20E) or 0)
            unit = _PLANE_UNIT_MM.get(int(sub.get(0xA210) or 2))
            dims = (int(sub.get(0xA002) or 0), int(sub.get(0xA003) or 0))
            if not (f_mm > 0 and res > 0 and unit and dims in ((w, h), (h, w))):
                return None
            f = f_mm * res / unit
    except Exception:  # PIL raises struct.error, TypeError, ZeroDivisionError... on bad EXIF
        return None
    lo, hi = FOCAL_RANGE
    return float(f) if math.isfinite(f) and lo <= f / max(w, h) <= hi else None


def _gps_degrees(dms, ref, negative: str) -> float:
    """Degrees from EXIF's (degrees, minutes, seconds) rationals and their N/S or E/W ref (a
    camera writing signed degrees, SRATIONAL, gives the sign by them where the ref does not)."""
    d, m, sec = (float(v) for v in dms)
    value = abs(d) + m / 60.0 + sec / 3600.0
    if isinstance(ref, bytes):
        ref = ref.decode("ascii", "replace")
    ref = str(ref).strip("\x00 ").upper()
    return -value if ref.startswith(negative) or (d < 0 and not ref) else value


def exif_gps(img: Image.Image) -> list[float] | None:
    """[latitude, longitude, altitude] of the camera from the photo's EXIF GPS tags (degrees
    north and east, WGS84; metres above sea level), or None where any of the three is missing,
    unreadable or out of range, or the position is the (0, 0) placeholder some cameras write
    before their GPS has a fix. A drone writes all three into every photo; most phones too."""
    try:
        g = img.getexif().get_ifd(0x8825)
        if not all(k in g for k in (2, 4, 6)):
            return None
        lat = _gps_degrees(g[2], g.get(1, "N"), "S")
        lon = _gps_degrees(g[4], g.get(3, "E"), "W")
        alt = float(g[6])
        below = g.get(5, 0)  # 1: below sea level; BYTE, UNDEFINED, SHORT or ASCII as written
        if isinstance(below, bytes):
            below = below[:1] in (b"\x01", b"1")
        elif isinstance(below, str):
            below = below.strip("\x00 ") == "1"
        if below:
            alt = -alt
    except Exception:  # PIL raises struct.error, TypeError, ZeroDivisionError... on bad EXIF
        return None
    if not all(math.isfinite(v) for v in (lat, lon, alt)):
        return None
    if abs(lat) > 90 or abs(lon) > 180 or (lat == 0 and lon == 0) or abs(alt) > 20000:
        return None
    return [lat, lon, alt]


def _decode(
    data: bytes, label: str
) -> tuple[Image.Image, str, int, float | None, list[float] | None]:
    """Fully decode ``data``; return (RGB image with EXIF orientation applied, format, the EXIF
    orientation tag (1 if none), the focal length in pixels from EXIF or None, the GPS position
    from EXIF or None). Raises ``InputError`` naming ``label``."""
    if not data:
        raise InputError(f"image {label} is empty (0 bytes)")
    if ImageFile.LOAD_TRUNCATED_IMAGES:
        raise InputError(
            "PIL.ImageFile.LOAD_TRUNCATED_IMAGES is set in this process, so truncated images "
            "cannot be detected; unset it"
        )
    try:
        img = Image.open(io.BytesIO(data))
        fmt = img.format or "?"
        if fmt not in _FORMATS:
            raise InputError(f"image {label} is {fmt}, not JPEG or PNG: convert it first")
        img.load()
        orientation = _orientation(img, label)
        focal = exif_focal_px(img)
        gps = exif_gps(img)
        if orientation in _UPRIGHT:
            img = img.transpose(_UPRIGHT[orientation])
        if img.mode in ("I", "I;16", "I;16B", "I;16L", "I;16N"):  # 16-bit greyscale PNG
            img = _grey16_to_8(img)
        if img.mode != "RGB":
            img = img.convert("RGB")
    except InputError:
        raise
    except UnidentifiedImageError:
        if data[4:8] == b"ftyp" and data[8:12] in (b"heic", b"heix", b"mif1", b"msf1", b"hevc"):
            raise InputError(  # a phone's or cloud export's HEIC named .jpg
                f"image {label} is HEIC whatever its name says, which CropCraft does not read: "
                "convert it to JPEG or PNG"
            ) from None
        raise InputError(f"image {label} is not a readable JPEG or PNG (corrupt?)") from None
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
        raise InputError(f"image {label} cannot be decoded (corrupt or truncated): {e}") from None
    return img, fmt, orientation, focal, gps


def ingest_images(
    source: str | os.PathLike,
    dest_dir: str | os.PathLike,
    max_size: int | None = None,
    *,
    min_images: int = 3,
    output_format: str = "png",
) -> IngestManifest:
    """Read every photo in the folder or fsspec URL ``source`` (``s3://bucket/plot1/``, ...),
    check and normalise it, and write it to ``dest_dir`` with ``manifest.json``.

    max_size: downscale (Lanczos) so that the longer side is at most this many pixels; None keeps
    the size.  min_images: fewer distinct images than this is an error.  output_format: 'png'
    (lossless, default) or 'jpg' (quality 95). Written names are the source stems plus the
    output extension (a numeric suffix separates stems that collide).

    Raises ``InputError`` naming the file for an empty, corrupt, truncated or unsupported image,
    and for fewer than ``min_images`` distinct images; ``OutputError`` if ``dest_dir`` cannot be
    written.
    """
    if output_format not in ("png", "jpg"):
        raise InputError(f"output format must be png or jpg, got {output_format!r}")
    if max_size is not None and int(max_size) < 16:
        raise InputError(f"max_size must be at least 16 pixels, got {max_size}")
    source = os.fspath(source)
    fs, files, root, folders = _list_source(source)
    dest = Path(dest_dir)
    try:
        dest.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"cannot create {dest}: {e}") from None

    def unsupported(base: str) -> InputError:
        return InputError(
            f"image {base} in {source} is {PurePosixPath(base).suffix[1:].upper()}, which "
            "CropCraft does not read: convert it to JPEG or PNG"
        )

    photos, ignored, companions = [], [], []
    for f in files:
        base = PurePosixPath(f).name
        ext = PurePosixPath(base).suffix.lower()
        if base.startswith("."):
            ignored.append(base)
        elif ext in IMAGE_EXTENSIONS:
            photos.append(f)
        elif ext in COMPANION_EXTENSIONS:  # ignored beside photos, named without any
            companions.append(base)
            ignored.append(base)
        elif ext in UNSUPPORTED_EXTENSIONS:
            raise unsupported(base)
        else:
            ignored.append(base)
    if companions and not photos:
        raise unsupported(companions[0])

    seen: dict[str, str] = {}
    used_names: set[str] = set()
    images: list[IngestedImage] = []
    duplicates: list[dict[str, str]] = []
    unreadable: list[str] = []  # every bad photo named at once, not one a night
    for f in photos:
        base = PurePosixPath(f).name
        try:
            with fs.open(f, "rb") as fh:
                data = fh.read()
        except OSError as e:
            raise InputError(f"cannot read image {base} from {source}: {e}") from None
        try:
            img, fmt, orientation, focal, gps = _decode(data, base)
        except InputError as e:
            unreadable.append(str(e))
            continue
        if unreadable:  # the rest are only checked
            continue
        sw, sh = img.size
        px = hashlib.sha256(f"{sw}x{sh}:".encode() + img.tobytes()).hexdigest()
        if px in seen:
            duplicates.append({"source": base, "duplicate_of": seen[px]})
            continue
        seen[px] = base
        scale = 1.0
        if max_size is not None and max(sw, sh) > int(max_size):
            scale = int(max_size) / max(sw, sh)
            size = (max(1, round(sw * scale)), max(1, round(sh * scale)))
            img = img.resize(size, Image.Resampling.LANCZOS)
            scale = size[0] / sw
        # a name the store can key: a Windows zip unpacked here names its photos
        # "DCIM\\100MEDIA\\DJI_0001.JPG", and the run failed on an internal store-key error
        # after decoding every photo (session 94's folders audit)
        stem = _short(_UNKEYABLE.sub("_", PurePosixPath(base).stem))
        name = f"{stem}.{output_format}"
        k = 1
        while name in used_names:
            name = f"{stem}_{k}.{output_format}"
            k += 1
        used_names.add(name)
        out = dest / name
        tmp = dest / f".{name}.tmp"
        try:
            if output_format == "png":
                img.save(tmp, format="PNG")
            else:
                img.save(tmp, format="JPEG", quality=95, subsampling=0)
            os.replace(tmp, out)
        except OSError as e:
            raise OutputError(f"cannot write {out}: {e}") from None
        images.append(
            IngestedImage(
                name=name,
                source=base,
                sha256_file=hashlib.sha256(data).hexdigest(),
                sha256_pixels=px,
                width=img.size[0],
                height=img.size[1],
                source_width=sw,
                source_height=sh,
                exif_orientation=orientation,
                scale=float(scale),
                format=fmt,
                focal_px=None if focal is None else focal * float(scale),
                gps=gps,
            )
        )
    if unreadable:
        more = f" (and {len(unreadable) - 8} more)" if len(unreadable) > 8 else ""
        raise InputError(
            (f"{len(unreadable)} of the {len(photos)} photos in {source} cannot be read: " if
             len(unreadable) > 1 else "")
            + "; ".join(unreadable[:8]) + more
        )  # fmt: skip
    if len(images) < min_images:
        extra = f" after dropping {len(duplicates)} duplicate(s)" if duplicates else ""
        raise InputError(
            f"{source} holds {len(images)} distinct JPEG/PNG image(s){extra}; at least "
            f"{min_images} are needed"
        )
    manifest = IngestManifest(
        source=source,
        dest_dir=str(dest),
        max_size=None if max_size is None else int(max_size),
        images=images,
        duplicates=duplicates,
        ignored=ignored,
        in_subfolders=photos_in_subfolders(fs, root, folders),
    )
    tmp = dest / f".{MANIFEST_NAME}.tmp"
    try:
        tmp.write_text(json.dumps(manifest.to_dict(), indent=2), encoding="utf-8")
        os.replace(tmp, dest / MANIFEST_NAME)
    except OSError as e:
        raise OutputError(f"cannot write {dest / MANIFEST_NAME}: {e}") from None
    return manifest
