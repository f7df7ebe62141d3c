"""The service's console entry points: the command, or one line naming what to install.

The server's commands (``svrnet-server``, ``svrnet-worker``, ``svrnet-mrd``, ``svrnet-mrd-send``)
need the ``server`` extra. The distribution installs them with the ``client`` extra too (one
package, three extras); there, a server command says what to install instead of failing with a
traceback. This module imports nothing beyond the standard library and :mod:`client.launch`
(itself the standard library only), whose launcher ``svrnet`` and ``svrnet-train`` share.

Example:
    >>> import subprocess, sys
    >>> code = "import sys; sys.modules['fastapi'] = None; from service.launch import server; server()"
    >>> done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    >>> done.returncode, "pip install" in done.stderr, "Traceback" in done.stderr
    (1, True, False)
"""

from __future__ import annotations

import os

SERVER_PACKAGES = ("numpy", "scipy", "fastapi", "fastapi_offline", "starlette", "anyio", "uvicorn", "pydantic",
                   "pydantic_settings", "multipart", "python_multipart", "onnxruntime", "SimpleITK",
                   "prometheus_client", "PIL", "pydicom", "nibabel", "websockets", "ismrmrd", "threadpoolctl", "isal")
"""The top-level modules the ``server`` extra installs (and what they bring)."""


def run_entry_point(command: str, target: str) -> None:
    """Call ``target`` (``"module:function"``) for ``command``; where importing its module misses one
    of :data:`SERVER_PACKAGES`, exit 1 with one line naming it and the extra to install
    (:func:`client.launch.run_or_name_missing`, which ``svrnet`` and ``svrnet-train`` use too)."""
    from client.launch import run_or_name_missing     # the standard library only, in every extra

    module, _, function = target.partition(":")
    run_or_name_missing(module, SERVER_PACKAGES, f"{command}: the server's packages are not installed ({{name}} is "
                        "missing): pip install \"svrnet[server]\" (in a checkout: make serve)", entry=function)


def private_files() -> None:
    """Files the process creates from now on are readable by its own user only (umask 077): set
    before the service's imports, some of which write files of their own (onnxruntime a session
    file in the temporary folder), as well as by :func:`~service.core.settings.load_settings`.

    Nor does a crash write a core dump (``RLIMIT_CORE`` 0, soft and hard, inherited by the job
    workers): a decoder or the network failing on a client's file would otherwise leave the
    process's memory, every upload and image it held, on disk (a container's limit is often
    unlimited, its core files in the working folder).
    """
    os.umask(0o077)
    try:
        import resource
    except ImportError:                                 # not a POSIX system: no core files to stop
        return
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))


def server() -> None:
    """Run ``svrnet-server`` (:func:`service.main.run`)."""
    private_files()
    run_entry_point("svrnet-server", "service.main:run")


def worker() -> None:
    """Run ``svrnet-worker`` (:func:`service.main.run_worker`)."""
    private_files()
    run_entry_point("svrnet-worker", "service.main:run_worker")


def mrd_server() -> None:
    """Run ``svrnet-mrd`` (:func:`service.mrd.server.run`)."""
    private_files()
    run_entry_point("svrnet-mrd", "service.mrd.server:run")


def mrd_send() -> None:
    """Run ``svrnet-mrd-send`` (:func:`service.mrd.send.run`)."""
    run_entry_point("svrnet-mrd-send", "service.mrd.send:run")
