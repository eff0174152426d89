"""Download a MipNeRF-360 scene: the official archive with a progress bar and resume, then only
the requested scene extracted."""

from __future__ import annotations

import logging
import os
import shutil
import time
import urllib.error
import urllib.request
import zipfile

from ..errors import InputError

__all__ = ["MIPNERF360_SCENES", "download", "download_mipnerf360", "extract_scene"]

log = logging.getLogger("cdcgs")

MIPNERF360_URL = "http://storage.googleapis.com/gresearch/refraw360/360_v2.zip"
MIPNERF360_SCENES = ("bicycle", "bonsai", "counter", "flowers", "garden", "kitchen", "room", "stump", "treehill")
CHUNK = 1 << 20


def download(url: str, path: str, *, retries: int = 5, progress: bool = True, timeout: float = 60.0) -> str:
    """Fetch ``url`` to ``path``, resuming a partial ``path + '.part'`` with an HTTP Range request.

    A dropped connection is retried (``retries`` times), each time from where it stopped. A server
    that ignores Range starts over. Returns ``path``.
    """
    from tqdm import tqdm

    if os.path.isfile(path):
        return path
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    part = path + ".part"
    bar = None
    try:
        for attempt in range(retries + 1):
            have = os.path.getsize(part) if os.path.isfile(part) else 0
            request = urllib.request.Request(url, headers={"Range": f"bytes={have}-"} if have else {})
            try:
                with urllib.request.urlopen(request, timeout=timeout) as response:
                    if have and response.status != 206:
                        have = 0  # the server ignored the range: start over
                    length = response.headers.get("Content-Length")
                    total = have + int(length) if length is not None else None
                    if bar is None:
                        bar = tqdm(
                            total=total,
                            initial=have,
                            unit="B",
                            unit_scale=True,
                            desc=os.path.basename(path),
                            disable=not progress,
                        )
                    else:
                        bar.reset(total=total)
                        bar.update(have)
                    with open(part, "ab" if have else "wb") as f:
                        while True:
                            chunk = response.read(CHUNK)
                            if not chunk:
                                break
                            f.write(chunk)
                            bar.update(len(chunk))
                    if total is not None and os.path.getsize(part) < total:
                        raise ConnectionError(f"connection closed at {os.path.getsize(part)} of {total} bytes")
                os.replace(part, path)
                return path
            except urllib.error.HTTPError as err:
                if err.code == 416 and have:  # asked past the end: the part is complete
                    os.replace(part, path)
                    return path
                raise InputError(url, f"the server answered HTTP {err.code} {err.reason}") from None
            except (ConnectionError, TimeoutError, urllib.error.URLError, OSError) as err:
                if attempt == retries:
                    raise InputError(
                        url,
                        f"download failed after {retries + 1} attempts ({err}); run the command again to resume from {part}",
                    ) from None
                log.warning("download interrupted (%s); resuming", err)
                time.sleep(min(2**attempt, 30) * 0.1)
    finally:
        if bar is not None:
            bar.close()
    return path


def extract_scene(archive: str, scene: str, dest: str) -> str:
    """Extract only the members under ``scene/`` (at any depth of a leading folder) into ``dest``."""
    try:
        zf = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, OSError) as err:
        raise InputError(archive, f"not a readable zip archive ({err}); delete it to download again") from None
    with zf:
        members = [m for m in zf.infolist() if f"/{scene}/" in f"/{m.filename}" and not m.is_dir()]
        if not members:
            raise InputError(archive, f"the archive holds no scene {scene!r}")
        prefix = members[0].filename[: f"/{members[0].filename}".index(f"/{scene}/")]
        target = os.path.join(dest, scene)
        for member in members:
            relative = member.filename[len(prefix) :]
            out = os.path.normpath(os.path.join(dest, relative))
            if not out.startswith(os.path.normpath(dest) + os.sep):
                raise InputError(archive, f"unsafe path in the archive: {member.filename!r}")
            if os.path.isfile(out) and os.path.getsize(out) == member.file_size:
                continue  # already extracted (a previous run was interrupted)
            os.makedirs(os.path.dirname(out), exist_ok=True)
            with zf.open(member) as src, open(out + ".part", "wb") as dst:
                shutil.copyfileobj(src, dst, CHUNK)
            os.replace(out + ".part", out)
    return target


def download_mipnerf360(
    scene: str, dest: str = "data/360_v2", url: str | None = None, keep_archive: bool = True, progress: bool = True
) -> str:
    """Download the MipNeRF-360 archive (resumable) and extract ``scene`` into ``dest/scene``."""
    if url is None and scene not in MIPNERF360_SCENES:
        raise ValueError(f"unknown MipNeRF-360 scene {scene!r}; the scenes are {', '.join(MIPNERF360_SCENES)}")
    archive = os.path.join(dest, ".download", os.path.basename(url or MIPNERF360_URL))
    download(url or MIPNERF360_URL, archive, progress=progress)
    target = extract_scene(archive, scene, dest)
    if not keep_archive:
        os.remove(archive)
    else:
        log.warning("the archive stays in %s for other scenes (--delete-archive removes it)", archive)
    return target
