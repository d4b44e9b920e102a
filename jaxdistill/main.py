"""The distillation job: `python -m jaxdistill.main --flagfile=configs/bedroom.cfg`.

Flags (see jaxdistill/engine/config.py or --helpfull) are parsed once into a frozen DistillConfig;
train.run does the rest. Bad input stops with a message naming the file and field before any
compute; a NaN loss stops with the last good checkpoint kept (status 3); SIGINT/SIGTERM save a
checkpoint and exit with 130/143, so a scheduler can tell a stopped run from a finished one.
"""

from __future__ import annotations

import logging as std_logging
import sys

from absl import app, flags, logging

from jaxdistill.engine import config as config_lib
from jaxdistill.errors import InputError

FLAGS = flags.FLAGS


class QuietLibraries(std_logging.Filter):
    """Drops INFO (and lower) records of orbax: a line per file per checkpoint drowns our log."""

    def filter(self, record: std_logging.LogRecord) -> bool:
        return record.levelno >= std_logging.WARNING or "orbax" not in record.pathname


def main(argv) -> None:
    logging.get_absl_handler().addFilter(QuietLibraries())
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}; every setting is a --flag")
    from jaxdistill import pipeline
    from jaxdistill.engine.loop import NonFiniteLoss

    follower = None
    try:
        config = config_lib.config_from_flags(FLAGS)
        if "view" in FLAGS and FLAGS.view:
            follower = start_viewer(config)
        summary = pipeline.run(config)
    except InputError as err:
        raise app.UsageError(str(err)) from None
    except NonFiniteLoss as err:
        logging.error("%s", err)
        sys.exit(3)
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
    define_view_flags(FLAGS)
    app.run(main)
