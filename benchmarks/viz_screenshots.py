"""Screenshots of the default Rerun view of a recording, in a headless Chromium.

    python benchmarks/viz_screenshots.py run.rrd --out shots/run.png
    python benchmarks/viz_screenshots.py --record ../shared/data/euroc_MH_05_mono_15s \\
        --mode mono --rrd /tmp/m.rrd --out /tmp/m.png

Serves the recording with the rerun wheel's own web viewer (``python -m rerun
--serve-web``, loopback only) and opens it in ``chromium --headless`` (Debian
package ``chromium``) with software WebGL (SwiftShader). The page is a small
wrapper served here: the viewer in a full-window iframe plus an image whose
response this server delays by ``--wait`` seconds, so Chromium's ``--screenshot``
(taken at the page's load event) sees the viewer after the data has streamed in.
Every host other than 127.0.0.1 resolves to nothing (the viewer would otherwise
wait on web fonts; there is no network). Nothing is interactive: the shot shows
what a user sees on opening the file (the sink's default blueprint).
"""

from __future__ import annotations

import argparse
import http.server
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
from pathlib import Path

_GIF = bytes.fromhex("47494638396101000100800000000000ffffff21f90401000000002c000000000100010000020144003b")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_port(port: int, timeout_s: float) -> None:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.2)
    raise RuntimeError(f"nothing listens on 127.0.0.1:{port} after {timeout_s} s")


def _wrapper_server(viewer_url: str, wait_s: float, size: tuple[int, int]) -> http.server.ThreadingHTTPServer:
    """Serve ``/`` (iframe of the viewer + a delayed image) and ``/delay`` on loopback."""
    w, h = size
    page = (f"<!doctype html><html><body style='margin:0;overflow:hidden;background:#000'>"
            f"<iframe src='{viewer_url}' style='border:0;width:{w}px;height:{h}px'></iframe>"
            f"<img src='/delay' style='position:absolute;width:1px;height:1px'></body></html>").encode()

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - http.server API
            if self.path.startswith("/delay"):
                time.sleep(wait_s)
                body, kind = _GIF, "image/gif"
            else:
                body, kind = page, "text/html"
            self.send_response(200)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args) -> None:
            pass

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    return srv


def chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    raise RuntimeError("no Chromium found: apt-get install -y chromium")


def screenshot(rrd: Path, out: Path, wait_s: float = 40.0, size: tuple[int, int] = (1600, 1000),
               renderer: str = "webgl") -> Path:
    """Serve ``rrd`` with the rerun web viewer and save a ``size`` PNG of it to ``out``."""
    rrd, out = Path(rrd).resolve(), Path(out).resolve()
    if not rrd.is_file():
        raise FileNotFoundError(rrd)
    web, grpc = _free_port(), _free_port()
    viewer = subprocess.Popen(
        [sys.executable, "-m", "rerun", "--serve-web", "--bind", "127.0.0.1", "--port", str(grpc),
         "--web-viewer-port", str(web), "--hide-welcome-screen", str(rrd)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    srv = None
    try:
        _wait_port(web, 30.0)
        _wait_port(grpc, 30.0)
        src = urllib.parse.quote(f"rerun+http://127.0.0.1:{grpc}/proxy", safe="")
        srv = _wrapper_server(f"http://127.0.0.1:{web}/?url={src}&renderer={renderer}", wait_s, size)
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory() as profile:
            cmd = [chromium(), "--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                   "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                   "--ignore-gpu-blocklist", "--enable-webgl", "--hide-scrollbars",
                   "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
                   f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}",
                   f"--screenshot={out}", f"http://127.0.0.1:{srv.server_address[1]}/"]
            subprocess.run(cmd, check=True, timeout=wait_s + 120,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    finally:
        if srv is not None:
            srv.shutdown()
        os.killpg(viewer.pid, 15)
        viewer.wait(10)
    if not out.is_file():
        raise RuntimeError(f"Chromium wrote no screenshot to {out}")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("rrd", nargs="?", type=Path, help="recording to show (or --record)")
    p.add_argument("--record", type=Path, help="dataset folder: record it first with `vio run`")
    p.add_argument("--mode", default="auto", help="`vio run --mode` for --record")
    p.add_argument("--rrd", dest="rrd_out", type=Path, help="where --record writes the .rrd")
    p.add_argument("--out", type=Path, required=True, help="PNG to write")
    p.add_argument("--wait", type=float, default=40.0, help="seconds to let the viewer load")
    p.add_argument("--size", default="1600x1000", help="window size WxH in pixels")
    args, extra = p.parse_known_args(argv)
    rrd = args.rrd
    if args.record is not None:
        rrd = args.rrd_out or args.out.with_suffix(".rrd")
        subprocess.run([sys.executable, "-m", "vio.cli", "run", str(args.record), "--mode", args.mode,
                        "--rrd", str(rrd), "--no-progress", *extra], check=True)
    elif extra:
        p.error(f"unrecognized arguments: {extra}")
    if rrd is None:
        p.error("give an .rrd or --record DATASET")
    w, h = (int(v) for v in args.size.lower().split("x"))
    shot = screenshot(rrd, args.out, args.wait, (w, h))
    print(f"recording  {rrd} ({rrd.stat().st_size / 1e6:.1f} MB)")
    print(f"screenshot {shot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
