"""The ``tapecell`` command line: one module a subcommand in ``commands/``, on top of
``estimator``, ``cell`` and ``sim`` (loaded only by the subcommands that need it)."""
from tapecell import one_blas_thread as _one_blas_thread

_one_blas_thread()   # before any subcommand loads numpy (see tapecell.one_blas_thread)
