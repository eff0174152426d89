"""`cdcgs download` against a local HTTP server on 127.0.0.1: progress, resume, one scene only."""

import http.server
import io
import os
import threading
import zipfile

import pytest

from cdcgs.cli import main as cli_main
from cdcgs.datasets.download import download, download_mipnerf360
from cdcgs.errors import InputError


def make_archive() -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as zf:
        for scene in ("garden", "bonsai"):
            zf.writestr(f"{scene}/poses_bounds.npy", os.urandom(2000))
            zf.writestr(f"{scene}/images_4/IMG_0001.JPG", os.urandom(30_000))
            zf.writestr(f"{scene}/sparse/0/cameras.bin", os.urandom(64))
    return buffer.getvalue()


class RangeServer:
    """Serves one archive with Range support; the first ``drop_first`` responses are cut short."""

    def __init__(self, payload: bytes, drop_first: int = 1, honour_range: bool = True):
        self.payload, self.drop_first, self.honour_range = payload, drop_first, honour_range
        self.requests = []
        owner = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self):
                owner.requests.append(self.headers.get("Range"))
                start = 0
                if owner.honour_range and self.headers.get("Range"):
                    start = int(self.headers["Range"].split("=")[1].split("-")[0])
                body = owner.payload[start:]
                self.send_response(206 if start else 200)
                self.send_header("Content-Length", str(len(body)))
                if start:
                    self.send_header("Content-Range", f"bytes {start}-{len(owner.payload) - 1}/{len(owner.payload)}")
                self.end_headers()
                if len(owner.requests) <= owner.drop_first:
                    self.wfile.write(body[: len(body) // 3])  # then hang up
                    self.close_connection = True
                    return
                self.wfile.write(body)

            def log_message(self, *args):
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/360_v2.zip"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def archive():
    return make_archive()


def test_download_resumes_and_extracts_only_the_scene(tmp_path, archive):
    server = RangeServer(archive, drop_first=1)
    try:
        path = download_mipnerf360("garden", dest=str(tmp_path), url=server.url, progress=False)
    finally:
        server.close()
    assert path == str(tmp_path / "garden")
    assert server.requests[0] is None and server.requests[1].startswith("bytes=") and server.requests[1] != "bytes=0-"
    assert (tmp_path / ".download" / "360_v2.zip").read_bytes() == archive
    assert sorted(os.listdir(tmp_path)) == [".download", "garden"]
    with zipfile.ZipFile(io.BytesIO(archive)) as zf:
        assert (tmp_path / "garden" / "images_4" / "IMG_0001.JPG").read_bytes() == zf.read(
            "garden/images_4/IMG_0001.JPG"
        )
        assert (tmp_path / "garden" / "sparse" / "0" / "cameras.bin").read_bytes() == zf.read(
            "garden/sparse/0/cameras.bin"
        )


def test_resume_across_runs_and_server_without_range(tmp_path, archive):
    # A partial file from an earlier run is continued; a server that ignores Range starts over.
    part = tmp_path / "a.zip.part"
    part.write_bytes(archive[:5000])
    server = RangeServer(archive, drop_first=0, honour_range=False)
    try:
        download(server.url, str(tmp_path / "a.zip"), progress=False)
    finally:
        server.close()
    assert (tmp_path / "a.zip").read_bytes() == archive and not part.exists()


def test_cli_download_and_errors(tmp_path, archive, capsys):
    server = RangeServer(archive, drop_first=0)
    try:
        assert (
            cli_main(
                [
                    "download",
                    "mipnerf360",
                    "--scene",
                    "bonsai",
                    "--dest",
                    str(tmp_path),
                    "--url",
                    server.url,
                    "--delete-archive",
                ]
            )
            == 0
        )
        assert "bonsai is in" in capsys.readouterr().out
        assert (
            not (tmp_path / ".download" / "360_v2.zip").exists() and (tmp_path / "bonsai" / "poses_bounds.npy").exists()
        )
        assert (
            cli_main(
                ["download", "mipnerf360", "--scene", "kitchen", "--dest", str(tmp_path / "k"), "--url", server.url]
            )
            == 2
        )
        assert "the archive holds no scene 'kitchen'" in capsys.readouterr().err
    finally:
        server.close()
    with pytest.raises(ValueError, match="unknown MipNeRF-360 scene"):
        download_mipnerf360("gardn", dest=str(tmp_path))
    with pytest.raises(InputError, match="download failed"):
        download("http://127.0.0.1:9/none.zip", str(tmp_path / "n.zip"), retries=1, progress=False)
