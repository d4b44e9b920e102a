"""The distillation job: `python -m jaxdistill.main --flagfile=configs/bedroom.cfg`, or from any
folder of an installed package `jaxdistill distill --config=bedroom`.

`--config=NAME` names a config shipped in the package (jaxdistill/configs/NAME.cfg: bedroom,
smoke, thesis) and stands for `--flagfile=` that file, in its place on the command line, so
flags after it override its values. Flags (see jaxdistill/engine/config.py or --helpfull) are
parsed once into a frozen DistillConfig; pipeline.run does the rest. Bad input stops with a message naming the file and field before any
compute; a NaN loss stops with the last good checkpoint kept (status 3); SIGINT/SIGTERM save a
checkpoint and exit with 130/143, so a scheduler can tell a stopped run from a finished one.
"""

from __future__ import annotations

from jaxdistill import huge_pages

if __name__ == "__main__":      # before JAX is imported: glibc reads its tunables at start-up
    huge_pages.run_again_with_huge_pages()

import logging as std_logging
import sys
from pathlib import Path

from absl import app, flags, logging

from jaxdistill.engine import config as config_lib
from jaxdistill.errors import InputError

FLAGS = flags.FLAGS
CONFIGS_DIR = Path(__file__).resolve().parent / "configs"


class QuietLibraries(std_logging.Filter):
    """Drops INFO (and lower) records of orbax: a line per file per checkpoint drowns our log."""

    def filter(self, record: std_logging.LogRecord) -> bool:
        return record.levelno >= std_logging.WARNING or "orbax" not in record.pathname


def main(argv) -> None:
    logging.get_absl_handler().addFilter(QuietLibraries())
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}; every setting is a --flag")
    if FLAGS.config is not None:         # only a --config inside a flagfile reaches here unexpanded
        raise app.UsageError(f"--config={FLAGS.config} inside a flagfile: give --config on the command line, or "
                             f"--flagfile={config_path(FLAGS.config)} in the flagfile")
    from jaxdistill import pipeline
    from jaxdistill.engine import distributed
    from jaxdistill.engine.loop import NonFiniteLoss

    follower = None
    try:
        config = config_lib.config_from_flags(FLAGS)
        distributed.initialize(config.coordinator_address, config.num_processes, config.process_id)
        if "view" in FLAGS and FLAGS.view and distributed.is_primary():
            from jaxdistill.export import usd
            usd.usd_available()       # pxr loaded before the viewer's threads start (`usd.usd_available`)
            follower = start_viewer(config)
        summary = pipeline.run(config)
    except InputError as err:
        distributed.announce_failure(err)        # the other processes of a run stop with it too
        raise app.UsageError(str(err)) from None
    except NonFiniteLoss as err:
        logging.error("%s", err)
        sys.exit(3)
    except distributed.PeerFailed as err:
        logging.error("%s", err)
        sys.exit(1)
    except (Exception, KeyboardInterrupt) as err:
        distributed.announce_failure(err)
        raise
    finally:
        if follower is not None and sys.exc_info()[0] is not None:
            follower.stop()
    if follower is not None:
        if not summary.get("stopped_by"):
            logging.warning("the run has ended; the viewer keeps serving it at %s until Ctrl-C", follower.url)
            follower.wait()
        follower.stop()
    if summary.get("stopped_by"):          # SIGINT/SIGTERM: checkpoint saved, but not finished
        sys.exit(summary["exit_status"])


def config_names() -> list[str]:
    """The names of the configs shipped in the package (jaxdistill/configs/*.cfg)."""
    return sorted(p.stem for p in CONFIGS_DIR.glob("*.cfg"))


def config_path(name: str) -> Path:
    """The flagfile of the shipped config `name`; SystemExit naming the shipped ones when there is none."""
    path = CONFIGS_DIR / f"{name}.cfg"
    if not name or Path(name).name != name or not path.is_file():
        sys.exit(f"--config={name}: no such config in this installation; the configs are "
                 f"{', '.join(config_names())} (or give a file with --flagfile=PATH)")
    return path


def expand_configs(argv: list[str]) -> list[str]:
    """argv with each `--config=NAME` (or `--config NAME`) replaced by `--flagfile=<its file>` in place."""
    out, args = [], iter(argv)
    for arg in args:
        if arg in ("--config", "-config"):
            arg = f"--config={next(args, '')}"
        if arg.startswith(("--config=", "-config=")):
            arg = f"--flagfile={config_path(arg.split('=', 1)[1])}"
        out.append(arg)
    return out


def define_config_flag(fv) -> None:
    flags.DEFINE_string("config", None, f"a config shipped with the package, by name ({', '.join(config_names())}; "
                        "bedroom is the default run): the same as --flagfile=<the package's configs/NAME.cfg>, "
                        "read where it stands, so flags after it override its values", flag_values=fv,
                        module_name=sys.argv[0])


def define_view_flags(fv) -> None:
    flags.DEFINE_bool("view", False, "serve the browser viewer of this run (needs the view extra) and keep "
                      "serving after it ends, until Ctrl-C; maps refresh at each checkpoint (--ckpt_every)",
                      flag_values=fv)
    flags.DEFINE_integer("view_port", 8080, "port of --view's viewer (on 127.0.0.1)", flag_values=fv)


def start_viewer(config):
    """The viewer following this run (--view), its port and installation checked before any compute."""
    from jaxdistill import view

    follower = view.Follower(config.out_dir, port=FLAGS.view_port)
    if not config.ckpt_every:
        logging.warning("--view: with --ckpt_every=0 the viewer shows the initial texels until the run ends; set "
                        "--ckpt_every to see the maps as they are distilled")
    logging.warning("--view: open %s in a browser (the viewer starts once the run's set-up is done)", follower.url)
    return follower


if __name__ == "__main__":
    config_lib.define_flags(FLAGS, main_module=True)
    define_config_flag(FLAGS)
    define_view_flags(FLAGS)
    app.run(main, argv=expand_configs(sys.argv))
