"""The server's console entry point: ``--help`` serves nothing, ``--host``/``--port`` override the settings."""

from __future__ import annotations

import pytest

from service import main
from client.launch import installed_version


@pytest.fixture
def kept_logging(monkeypatch: pytest.MonkeyPatch) -> None:
    """A command started in the test process leaves the process's logging as it is: ``configure`` would
    send the ``service`` loggers to the stderr of the test that ran it (closed for later tests)."""
    import logging

    monkeypatch.setattr(main.service_logging, "configure", lambda *args, **kwargs: None)
    monkeypatch.setattr(logging.getLogger("service"), "handlers", [])
    monkeypatch.setattr(logging.getLogger("service"), "propagate", True)


@pytest.mark.usefixtures("kept_logging")
def test_help_serves_nothing_and_options_override_the_environment(monkeypatch: pytest.MonkeyPatch,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    served: list = []
    monkeypatch.setattr("uvicorn.Server.run", lambda server, sockets=None: served.append(server.config))
    monkeypatch.setattr(main, "create_app", lambda settings, *models: settings)
    monkeypatch.setattr(main.ModelRegistry, "from_directory", classmethod(lambda cls, *args: None))
    monkeypatch.setattr(main.Localisers, "from_directory", classmethod(lambda cls, *args: cls({})))
    with pytest.raises(SystemExit) as end:
        main.run(["--help"])
    assert end.value.code == 0 and "SVRNET_" in capsys.readouterr().out and not served
    with pytest.raises(SystemExit) as end:                  # a lab filing a bug says which release
        main.run(["--version"])
    assert end.value.code == 0 and capsys.readouterr().out.strip() == f"svrnet-server {installed_version()}"
    assert installed_version() is not None and not served       # the test environment installs the package
    monkeypatch.setenv("SVRNET_PORT", "8123")
    main.run([])
    main.run(["--port", "9001", "--host", "0.0.0.0"])
    assert [(s.host, s.port) for s in served] == [("127.0.0.1", 8123), ("0.0.0.0", 9001)]
    assert served[0].ws_ping_timeout == 60.0 and served[0].ws_ping_interval == 20.0
    assert served[0].timeout_graceful_shutdown == main.SHUTDOWN_GRACE_S
    with pytest.raises(SystemExit) as end:
        main.run(["--port", "0"])
    assert str(end.value.code).startswith("svrnet-server: SVRNET_PORT:") and len(served) == 2


@pytest.mark.parametrize(("variable", "value", "said"), [
    ("SVRNET_LOG_LEVEL", "verbose", "one of debug"),
    ("SVRNET_QUEUE_URL", "http://127.0.0.1:6379", "redis://"),
    ("SVRNET_MODELS_DIR", "{tmp}/none", "holds no <name>/model.onnx"),
    ("SVRNET_DEFAULT_MODEL", "huge", "no model 'huge'"),
    ("SVRNET_LOCALISERS_DIR", "{tmp}/localisers", "none named default"),   # stacks without masks would all fail
    ("SVRNET_DATA_DIR", "{tmp}/a_file/below", "cannot be created"),
    ("SVRNET_TMP_DIR", "{tmp}/none", "not a folder"),
    ("SVRNET_API_KEYS", " , ", "no key"),
    ("SVRNET_API_KEYS", "0123456789abcdef0123,secret", "a key of 6 characters is guessed by trying"),
    ("SVRNET_MAX_UPLOAD_MB", "inf", "finite number"),          # no limit at all: refused, not a traceback
    ("SVRNET_JOB_TIMEOUT_H", "inf", "finite number"),
])
def test_a_setting_that_cannot_work_stops_every_command_in_one_line_naming_it(
        variable: str, value: str, said: str, tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: ANN001
    """Not a server that passes its health check and fails every request, nor a traceback."""
    from service.jobs import worker_cli
    from service.mrd import server as mrd_server

    (tmp_path / "a_file").write_text("")
    (tmp_path / "localisers" / "quick").mkdir(parents=True)
    (tmp_path / "localisers" / "quick" / "model.onnx").write_bytes(b"")
    monkeypatch.setenv("SVRNET_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv(variable, value.format(tmp=tmp_path))
    monkeypatch.setattr("uvicorn.Server.run", lambda server, sockets=None: pytest.fail("served with a setting that cannot work"))
    commands = [("svrnet-server", lambda: main.run([])), ("svrnet-worker", lambda: worker_cli.main([])),
                ("svrnet-mrd", lambda: mrd_server.main([]))]
    for prog, command in commands if variable != "SVRNET_DEFAULT_MODEL" else [commands[0], commands[2]]:
        with pytest.raises(SystemExit) as end:
            command()
        message = str(end.value.code)
        assert message.startswith(f"{prog}: ") and f"{variable}: " in message and said in message, message
        assert "\n" not in message


@pytest.mark.parametrize("variable", ["SVRNET_MODELS_DIR", "SVRNET_LOCALISERS_DIR"])
@pytest.mark.usefixtures("kept_logging")
def test_a_model_file_that_does_not_load_stops_the_servers_in_one_line_naming_it(
        variable: str, tmp_path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:  # noqa: ANN001
    """A truncated or foreign ``model.onnx``: the HTTP and MRD servers stop before serving, in one line
    that names the file and the setting of its folder (not a traceback from inside the start-up)."""
    import shutil

    from service.core.settings import Settings
    from service.mrd import server as mrd_server

    shipped = {"SVRNET_MODELS_DIR": Settings().models_dir, "SVRNET_LOCALISERS_DIR": Settings().localisers_dir}
    folder = tmp_path / "models"
    shutil.copytree(shipped[variable] / "default", folder / "default")
    (folder / "default" / "model.onnx").write_bytes(b"half a model")
    (folder / "copied-without-its-file").mkdir()
    monkeypatch.setenv("SVRNET_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv(variable, str(folder))
    monkeypatch.setattr("uvicorn.Server.run", lambda server, sockets=None: pytest.fail("served a broken model"))
    with pytest.raises(SystemExit) as end:
        main.run([])
    message = str(end.value.code)
    assert message.startswith(f"svrnet-server: {variable}: ") and "default/model.onnx does not load" in message
    assert "\n" not in message
    with pytest.raises(SystemExit) as end:
        mrd_server.main([])
    said = capsys.readouterr().err
    assert end.value.code == 2 and f"svrnet-mrd: {variable}: " in said and "Traceback" not in said


def test_a_folder_without_its_model_file_is_named_in_a_warning(tmp_path, caplog: pytest.LogCaptureFixture) -> None:  # noqa: ANN001
    """A model folder copied without ``model.onnx`` loads nothing and says so; dot folders (a model
    being shipped into place) are passed over in silence."""
    from service.core.onnx import load_models

    (tmp_path / "v2").mkdir()
    (tmp_path / ".v3.shipping").mkdir()
    with caplog.at_level("WARNING"):
        assert load_models(tmp_path, "SVRNET_MODELS_DIR", lambda path: path) == {}
    warned = [r for r in caplog.records if "without model.onnx" in r.getMessage()]
    assert [r.model for r in warned] == ["v2"] and "SVRNET_MODELS_DIR" in warned[0].getMessage()


def test_a_started_command_makes_its_files_private(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:  # noqa: ANN001
    import os

    from service.core.settings import load_settings

    monkeypatch.setenv("SVRNET_DATA_DIR", str(tmp_path))
    os.umask(0o022)
    load_settings("svrnet-server")
    (tmp_path / "upload").write_bytes(b"x")
    assert (tmp_path / "upload").stat().st_mode & 0o077 == 0


def test_a_second_server_on_a_store_in_use_is_refused_in_one_line(tmp_path, monkeypatch: pytest.MonkeyPatch,  # noqa: ANN001
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    from service.jobs.local_runner import lock_store

    monkeypatch.setattr("uvicorn.Server.run", lambda server, sockets=None: pytest.fail("served beside the store's owner"))
    monkeypatch.setenv("SVRNET_DATA_DIR", str(tmp_path))
    held = lock_store(tmp_path)                                          # the running server's
    try:
        with pytest.raises(SystemExit) as end:
            main.run([])
    finally:
        held.close()
    err = capsys.readouterr().err
    assert end.value.code == 1 and "belongs to another running svrnet-server" in err and "Traceback" not in err


def test_the_redis_back_end_without_the_queue_extra_is_named_in_one_line(monkeypatch: pytest.MonkeyPatch,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    import importlib.util

    from service.jobs import backends

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "rq" else real(name, *a))
    monkeypatch.setattr("uvicorn.Server.run", lambda server, sockets=None: pytest.fail("served without the queue's packages"))
    monkeypatch.setenv("SVRNET_QUEUE_URL", "redis://127.0.0.1:1/0")
    with pytest.raises(SystemExit) as end:
        main.run([])
    err = capsys.readouterr().err
    assert end.value.code == 1 and "rq is missing" in err and "svrnet[queue]" in err and "Traceback" not in err
    with pytest.raises(SystemExit) as end:
        main.run_worker()
    assert "svrnet-worker:" in str(end.value.code) and "rq is missing" in str(end.value.code)
    monkeypatch.setattr(importlib.util, "find_spec", real)
    assert backends.queue_extra_missing() is None                        # the dev extras hold the queue's


@pytest.mark.usefixtures("kept_logging")
def test_an_address_the_servers_cannot_listen_on_stops_them_before_they_start_naming_the_setting(
        tmp_path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:  # noqa: ANN001
    """A host name that does not resolve, or a port another program listens on: one line naming the
    setting, before any model loads (uvicorn said ``[Errno -2] Name or service not known`` after the
    whole start)."""
    import socket

    from service.mrd import server as mrd_server

    monkeypatch.setenv("SVRNET_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setattr(main.ModelRegistry, "from_directory", classmethod(lambda cls, *args: pytest.fail("loaded")))
    monkeypatch.setattr("uvicorn.Server.run", lambda server, sockets=None: pytest.fail("served"))
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        for variable, value, said in (("SVRNET_HOST", "no-such-host.invalid", "SVRNET_HOST: cannot listen on"),
                                      ("SVRNET_PORT", str(port), f"SVRNET_PORT: port {port} on 127.0.0.1 is in use")):
            monkeypatch.setenv(variable, value)
            with pytest.raises(SystemExit) as end:
                main.run([])
            assert str(end.value.code).startswith(f"svrnet-server: {said}"), end.value.code
            monkeypatch.delenv(variable)
        assert mrd_server.main(["--port", str(port)]) == 2
        assert capsys.readouterr().err.startswith(f"svrnet-mrd: --port: port {port} on 127.0.0.1 is in use")
