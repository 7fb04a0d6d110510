"""How ``usdrelight serve`` stops: on Ctrl-C (SIGINT) and on a plain kill (SIGTERM), cleanly, with exit 0."""
from __future__ import annotations

import contextlib
import signal


@contextlib.contextmanager
def stop_on_signals():
    """Within it, Ctrl-C (SIGINT) and a plain kill (SIGTERM) raise KeyboardInterrupt in the main thread, so that
    :meth:`usdrelight.serve.app.ServeApp.wait_forever` returns to a caller that stops the app cleanly; also when
    the process started with SIGINT ignored (``usdrelight serve ... &`` in a non-interactive script), where Python
    installs no handler of its own. The handlers before are put back on leaving."""
    before = {sig: signal.signal(sig, signal.default_int_handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)
