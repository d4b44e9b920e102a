"""`jaxdistill view OUT_DIR` / `python -m jaxdistill.view OUT_DIR`: look at a run in the browser.

Serves an interactive 3D view of a finished or running distillation (jaxdistill/viewer/): the
textured mesh with a map selector, the views' cameras, per-view comparisons, evidence colour
maps and the loss curve. Binds to 127.0.0.1 unless --host says otherwise; prints the URL.
Needs the `view` extra: `pip install -e ".[view]"` (viser).
"""

from __future__ import annotations

import argparse
import errno
import signal
import importlib.util
import socket
import sys
import threading
import zipfile
from pathlib import Path

from jaxdistill.errors import InputError

DEFAULT_PORT = 8080


def parse_args(argv):
    parser = argparse.ArgumentParser(prog="jaxdistill view", description=__doc__.split("\n\n")[0])
    parser.add_argument("out_dir", metavar="OUT_DIR", help="the --out_dir of a finished or running run")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"port to serve on (default {DEFAULT_PORT})")
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    parser.add_argument("--scene", default=None, help="the run's scene, when its recorded --scene does not read "
                        "from here (a relative path from another folder)")
    parser.add_argument("--refresh", type=float, default=2.0, help="seconds between checks for new checkpoints")
    return parser.parse_args(argv)


def check_port(host: str, port: int) -> None:
    """InputError naming the port when it is invalid or taken (before anything is loaded)."""
    if not 0 < port < 65536:
        raise InputError.single("flags", "--port", f"{port} is not a port number (1-65535)")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)     # as the server binds: TIME_WAIT is free
        try:
            sock.bind((host, port))
        except OSError as err:
            why = "is in use" if err.errno == errno.EADDRINUSE else f"cannot be bound ({err.strerror})"
            raise InputError.single("flags", "--port", f"{host}:{port} {why}; choose another --port") from None


def check_installed() -> None:
    """InputError saying how to install the view extra when viser is missing."""
    if importlib.util.find_spec("viser") is None:
        raise InputError.single("jaxdistill view", "(install)", "the viewer needs the view extra (viser is not "
                                'installed); install it with pip install -e ".[view]"')


def start(out_dir, *, host: str = "127.0.0.1", port: int = DEFAULT_PORT, scene: str | None = None):
    """The running Viewer of `out_dir` (viser's server threads serve it until `.close()`)."""
    check_installed()
    check_port(host, port)
    from jaxdistill.viewer.app import Viewer
    from jaxdistill.viewer.run import RunDir

    return Viewer(RunDir(out_dir, scene=scene), host=host, port=port)


class Follower:
    """The viewer of a run this process is running (the main job's --view): a thread waits for
    the run's set-up to write texel_space.npz, then serves and refreshes until `stop()`."""

    def __init__(self, out_dir, *, host: str = "127.0.0.1", port: int = DEFAULT_PORT, interval: float = 2.0):
        check_installed()
        check_port(host, port)
        self.out_dir, self.host, self.port, self.interval = Path(out_dir), host, port, interval
        self.url = f"http://{host}:{port}"
        self.stopping = threading.Event()
        self.viewer = None
        self.thread = threading.Thread(target=self._serve, name="jaxdistill-view", daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        from jaxdistill.export.run_dir import TEXEL_SPACE_FILE

        while self.viewer is None:
            if self.stopping.wait(0.5):
                return
            if not (self.out_dir / TEXEL_SPACE_FILE).is_file():
                continue
            try:
                self.viewer = start(self.out_dir, host=self.host, port=self.port)
            except InputError as err:
                print(f"jaxdistill view: {err}", file=sys.stderr)
                return
            except (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile) as err:   # a file caught mid-copy: retry
                print(f"jaxdistill view: not ready yet ({err}); retrying", file=sys.stderr)
        print(f"jaxdistill view: following the run at {self.url}", file=sys.stderr, flush=True)
        self.viewer.follow(self.stopping, self.interval)

    def wait(self) -> None:
        """Serves until Ctrl-C (the run has finished: its final maps stay on show)."""
        try:
            while self.thread.is_alive():
                self.thread.join(0.5)
        except KeyboardInterrupt:
            pass

    def stop(self) -> None:
        self.stopping.set()
        self.thread.join(10)
        if self.viewer is not None:
            self.viewer.close()


def main(argv=None) -> int:
    """The command line: `argv` is the arguments after the command (`OUT_DIR --port=...`;
    sys.argv[1:] when None). Returns the exit status: 0, or 2 for a user error."""
    args = parse_args(sys.argv[1:] if argv is None else argv)
    try:
        viewer = start(args.out_dir, host=args.host, port=args.port, scene=args.scene)
    except InputError as err:
        print(f"jaxdistill view: {err}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):        # stop between refreshes, never inside one
        signal.signal(signum, lambda *_: stop.set())
    print(f"jaxdistill view: serving {args.out_dir} at {viewer.url} (open it in a browser; Ctrl-C stops)", flush=True)
    try:
        viewer.follow(stop, args.refresh)
    finally:
        viewer.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
