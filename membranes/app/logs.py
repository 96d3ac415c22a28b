"""Quiet JIT compilation: dolfinx compiles each new form through setuptools, which logs every
build step ("running build_ext", the gcc command lines) as INFO records of the root logger,
after lowering the root level to INFO. The records of its distutils below WARNING are
dropped by a filter on the root logger; nothing else of the user's logging is touched."""

import logging


class _DistutilsChatter(logging.Filter):
    """Rejects the root logger's records below WARNING that setuptools' distutils made."""

    def filter(self, record):
        return record.levelno >= logging.WARNING or "distutils" not in record.pathname


def quiet_jit_logging():
    """Install the filter on the root logger, once (`solve`, the CLI, demos, tests)."""
    root = logging.getLogger()
    if not any(isinstance(f, _DistutilsChatter) for f in root.filters):
        root.addFilter(_DistutilsChatter())
