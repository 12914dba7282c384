"""Screenshots of the documentation site: build it, serve it on localhost and photograph
pages with headless Chromium, with every host but localhost unreachable, so the pictures
show what a reader without network access sees (formulas included: MathJax is vendored).

    python docs/screenshots.py                      # home, theory, real-data guide
    python docs/screenshots.py --out shots --width 800 theory/ guides/solvers/

Needs the docs extra (mkdocs) and a Chromium (`chromium`, e.g. Debian's package). Not
part of CI. Writes `<out>/<page>.png` (default `outputs/screenshots/`) and prints the paths.
"""

from __future__ import annotations

import argparse
import functools
import http.server
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PAGES = ["", "theory/", "guides/real-data/"]
BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def build(site: Path) -> None:
    """`mkdocs build --strict` of this checkout into `site`."""
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "--site-dir", str(site)],
        cwd=REPO,
        env=env,
        check=True,
    )


def serve(site: Path) -> tuple[http.server.ThreadingHTTPServer, str]:
    """An HTTP server for `site` on a free port of 127.0.0.1, running in a thread."""
    handler = functools.partial(_QuietHandler, directory=str(site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"http://127.0.0.1:{server.server_address[1]}/"


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


def screenshot(browser: str, url: str, png: Path, width: int, height: int) -> None:
    """Photograph `url` after its scripts have run (up to 20 s of virtual time); every
    host name but localhost fails to resolve."""
    with tempfile.TemporaryDirectory() as profile:
        subprocess.run(
            [
                browser,
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--hide-scrollbars",
                "--no-first-run",
                f"--user-data-dir={profile}",
                "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
                f"--window-size={width},{height}",
                "--virtual-time-budget=20000",
                f"--screenshot={png}",
                url,
            ],
            check=True,
            capture_output=True,
            timeout=120,
        )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("pages", nargs="*", default=PAGES, help="site paths (default: %(default)s)")
    parser.add_argument(
        "--out",
        type=Path,
        default=REPO / "outputs" / "screenshots",
        help="output folder (default: outputs/screenshots)",
    )
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=2000)
    parser.add_argument("--browser", default=None, help="Chromium executable")
    args = parser.parse_args(argv)
    browser = args.browser or next(filter(None, map(shutil.which, BROWSERS)), None)
    if browser is None:
        sys.exit(f"no Chromium found ({', '.join(BROWSERS)}); pass --browser")
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        site = Path(tmp) / "site"
        build(site)
        server, root = serve(site)
        try:
            for page in args.pages:
                name = page.strip("/").replace("/", "_") or "index"
                png = args.out / f"{name}.png"
                screenshot(browser, root + page.lstrip("/"), png, args.width, args.height)
                print(png)
        finally:
            server.shutdown()


if __name__ == "__main__":
    main()
