"""The distillation job: `python -m jaxdistill.main --flagfile=configs/bedroom.cfg`.

Flags (see jaxdistill/config.py or --helpfull) are parsed once into a frozen DistillConfig;
train.run does the rest. Bad input stops with a message naming the file and field before any
compute; a NaN loss stops with the last good checkpoint kept (status 3); SIGINT/SIGTERM save a
checkpoint and exit with 130/143, so a scheduler can tell a stopped run from a finished one.
"""

from __future__ import annotations

import logging as std_logging
import sys

from absl import app, flags, logging

from jaxdistill import config as config_lib
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
    from jaxdistill import train

    try:
        config = config_lib.config_from_flags(FLAGS)
        summary = train.run(config)
    except InputError as err:
        raise app.UsageError(str(err)) from None
    except train.NonFiniteLoss as err:
        logging.error("%s", err)
        sys.exit(3)
    if summary.get("stopped_by"):          # SIGINT/SIGTERM: checkpoint saved, but not finished
        sys.exit(summary["exit_status"])


if __name__ == "__main__":
    config_lib.define_flags(FLAGS, main_module=True)
    app.run(main)
