"""Compiled report templates kept between runs, so a run does not compile them again.

Jinja2 turns a template into Python code before it renders it: ~45 ms of CPU for the analysis
page, on every ``analyze``, ``plan`` and ``demo`` run although the template only changes with
the package. Jinja's own bytecode cache keeps that code in a folder of the user's own
(``$TMPDIR/_jinja2-cache-<uid>``, mode 0700, its owner checked; the temporary folder on
Windows) and uses a stored copy only while the template's source is unchanged (a checksum of
it is stored beside the code) and for the same Python version.

Two things are added here. The key of a stored template names the Jinja2 version, since code
compiled by one version calls that version's runtime. And the cache is never an error: a
folder that cannot be made or written, or a damaged file, means the template is compiled as
it would be without a cache (a report does not depend on a temporary folder).
"""

from __future__ import annotations

import contextlib
from typing import Any

__all__ = ["compiled_template_cache"]


def compiled_template_cache(directory: str | None = None) -> Any | None:
    """A Jinja2 bytecode cache for the package's templates, or None where none can be kept.

    Parameters
    ----------
    directory : str, optional
        Where compiled templates are kept (default: Jinja's per-user temporary folder).

    Returns
    -------
    jinja2.BytecodeCache or None
        None if the folder cannot be made or is not safely the user's own.

    Examples
    --------
    >>> import jinja2, tempfile
    >>> folder = tempfile.mkdtemp()
    >>> env = jinja2.Environment(bytecode_cache=compiled_template_cache(folder))
    >>> env.from_string("{{ 1 + 1 }}").render()  # from_string is never cached
    '2'
    """
    import jinja2

    class _Cache(jinja2.FileSystemBytecodeCache):
        def get_cache_key(self, name: str, filename: str | None = None) -> str:
            return super().get_cache_key(f"jinja2 {jinja2.__version__}\x00{name}", filename)

        def load_bytecode(self, bucket: Any) -> None:
            try:
                super().load_bytecode(bucket)
            except Exception:  # any damage means: compile it again
                bucket.reset()

        def dump_bytecode(self, bucket: Any) -> None:
            with contextlib.suppress(OSError):  # full or read-only: kept next time, or never
                super().dump_bytecode(bucket)

    try:
        return _Cache(directory)
    except (OSError, RuntimeError):  # no folder, or one that is not safely this user's
        return None
