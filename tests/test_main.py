"""The server's console entry point: ``--help`` serves nothing, ``--host``/``--port`` override the settings."""

from __future__ import annotations

import pytest

from service import main


def test_help_serves_nothing_and_options_override_the_environment(monkeypatch: pytest.MonkeyPatch,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    served: list[dict] = []
    monkeypatch.setattr("uvicorn.run", lambda app, **kw: served.append(kw))
    monkeypatch.setattr(main, "create_app", lambda settings: settings)
    with pytest.raises(SystemExit) as end:
        main.run(["--help"])
    assert end.value.code == 0 and "SVRNET_" in capsys.readouterr().out and not served
    monkeypatch.setenv("SVRNET_PORT", "8123")
    main.run([])
    main.run(["--port", "9001", "--host", "0.0.0.0"])
    assert [(s["host"], s["port"]) for s in served] == [("127.0.0.1", 8123), ("0.0.0.0", 9001)]
    assert served[0]["ws_ping_timeout"] == 60.0 and served[0]["ws_ping_interval"] == 20.0
    with pytest.raises(SystemExit) as end:
        main.run(["--port", "0"])
    assert end.value.code == 2 and "port" in capsys.readouterr().err and len(served) == 2
