"""`temoto router` for a process test's Zenoh URL; standard library only.

Runner scripts run inside ``unshare -n`` as ``python -c`` get this file's text prepended
(``_transports.ROUTER_CODE``); scripts of this folder import it.
"""

import subprocess
import sys


def start_router(url):  # type: ignore[no-untyped-def]
    """For a ``zenoh:`` URL, `temoto router` on its endpoint, announced when this returns.

    Returns None for any other URL (LCM needs no router).
    """
    if not url.startswith("zenoh:"):
        return None
    endpoint = url[len("zenoh:") :].split("?")[0]
    router = subprocess.Popen(
        [sys.executable, "-m", "temoto", "router", "--listen", endpoint],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    line = router.stdout.readline()  # bounded by the caller's timeout of the whole runner
    if "listening on" not in line:
        router.kill()
        raise SystemExit(f"temoto router did not start: {line}{router.communicate()[1]}")
    return router


def stop_router(router):  # type: ignore[no-untyped-def]
    """Stop what :func:`start_router` started (SIGTERM); it must exit 0."""
    if router is not None:
        router.terminate()
        _, err = router.communicate(timeout=10)
        if router.returncode != 0:
            raise SystemExit(f"temoto router exited {router.returncode}: {err}")
