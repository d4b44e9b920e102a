"""The `jaxdistill` command: `jaxdistill distill|estimate|precompute|import|view [flags]`.

Each subcommand is the module that `python -m` runs, imported only when chosen (so `jaxdistill
import` never loads JAX's distillation code, and help is instant): the rest of the command line
goes to it as its own, and its exit status is the command's. `view` calls `jaxdistill.view:main()`
(sys.argv = ["jaxdistill view", *args]; its return value is the exit status) and says so clearly
when this installation has no viewer.
"""

from __future__ import annotations

import importlib
import runpy
import sys

COMMANDS = {
    "distill": ("jaxdistill.main", "distil a scene's PBR texture maps (python -m jaxdistill.main)"),
    "estimate": ("jaxdistill.estimate", "per-view RGB<->X estimates of photos (python -m jaxdistill.estimate)"),
    "precompute": ("jaxdistill.precompute", "ray casts, texel layout and visibility of a scene (python -m "
                   "jaxdistill.precompute)"),
    "import": ("jaxdistill.import_scene", "import a dataset (fipt, iris, scannetpp, nerfstudio, colmap) as a "
               "scene folder"),
    "view": ("jaxdistill.view", "look at a run's outputs (jaxdistill.view:main)"),
}


def usage() -> str:
    """The command's help text."""
    width = max(map(len, COMMANDS))
    lines = ["usage: jaxdistill COMMAND [flags]   (jaxdistill COMMAND --help for a command's flags)", "",
             "commands:"]
    lines += [f"  {name:<{width}}  {what}" for name, (_, what) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv=None) -> int:
    """Runs the subcommand named in argv[1] (default sys.argv); returns the exit status."""
    argv = list(sys.argv if argv is None else argv)
    if len(argv) < 2 or argv[1] in ("-h", "--help", "help"):
        print(usage(), file=sys.stdout if len(argv) >= 2 else sys.stderr)
        return 0 if len(argv) >= 2 else 2
    name = argv[1]
    if name not in COMMANDS:
        print(f"jaxdistill: unknown command {name!r}; the commands are {', '.join(COMMANDS)}\n\n{usage()}",
              file=sys.stderr)
        return 2
    module = COMMANDS[name][0]
    sys.argv = [f"jaxdistill {name}", *argv[2:]]
    if name == "view":
        return _view(module)
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    except SystemExit as stop:               # absl's app.run and the import's sys.exit end here
        code = stop.code
        if code is None or isinstance(code, int):
            return code or 0
        print(code, file=sys.stderr)
        return 1
    return 0


def _view(module: str) -> int:
    """Calls `module.main()`; exit status 2 with what to do when the module is not installed."""
    try:
        viewer = importlib.import_module(module)
    except ModuleNotFoundError as err:
        if err.name != module:
            raise
        print(f"jaxdistill view: this installation has no viewer ({module} is not installed); update jaxdistill "
              "(pip install -e . in a checkout that has jaxdistill/view.py), or open the run's scene.glb in "
              "Blender and its maps/ and renders/ in an image viewer", file=sys.stderr)
        return 2
    if not callable(getattr(viewer, "main", None)):
        print(f"jaxdistill view: {module} has no main() to run", file=sys.stderr)
        return 2
    status = viewer.main()
    return status if isinstance(status, int) else 0


if __name__ == "__main__":
    sys.exit(main())
