"""skinmapd: the gateway service as a process -- the config, the port lock, the Zenoh session,
the console, signals and systemd around one `Gateway` (skinmap.daemon.gateway), which wires
the parts: scanner link, Notifier and listeners (processing, log), publisher, status and health.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import sys
import threading
from typing import TYPE_CHECKING, Callable, ContextManager

import skinmap
from skinmap.daemon.config import ConfigError, DaemonConfig, load_config
from skinmap.daemon.console import StatusConsole
from skinmap.daemon.gateway import Gateway, PoseInputFactory, limit_blas_threads
from skinmap.daemon.publisher import PublisherFactory

if TYPE_CHECKING:
    import zenoh

__all__ = ["Gateway", "main", "open_zenoh", "run_gateway", "setup_logging", "zenoh_publishers"]

log = logging.getLogger("skinmapd")

STOP_GRACE_S = 5.0  # after SIGTERM, the main loop must begin shutting down within this
BLOCK_CLOSE_KEY = "transport/link/tx/queue/congestion_control/block/wait_before_close"
ZENOH_DEFAULT_BLOCK_CLOSE_US = 5_000_000
BLOCK_CLOSE_US = 1_000_000


def open_zenoh(cfg: DaemonConfig) -> ContextManager[zenoh.Session | None]:
    """A context manager yielding the Zenoh session (or None when Zenoh is disabled)."""
    if not cfg.zenoh.enabled:
        return contextlib.nullcontext(None)
    from skinmap.daemon.zenoh_io import make_session_config, open_session

    zc = cfg.zenoh
    zconf = make_session_config(
        zc.listen, zc.connect, allow_non_loopback=zc.allow_non_loopback, mode=zc.mode,
        config_file=str(cfg.resolve(zc.config_file)) if zc.config_file else None,
        deny_remote_writes=cfg.guarded_key_expr(),
    )
    # A reply takes its query's congestion control (BLOCK by default), so a client that stops
    # reading holds up replies to it until Zenoh closes its link: after 1 s here instead of
    # Zenoh's 5 s, unless a Zenoh config file sets its own value.
    if json.loads(zconf.get_json(BLOCK_CLOSE_KEY)) == ZENOH_DEFAULT_BLOCK_CLOSE_US:
        zconf.insert_json5(BLOCK_CLOSE_KEY, str(BLOCK_CLOSE_US))
    return open_session(zconf)


def zenoh_publishers(cfg: DaemonConfig, session: zenoh.Session | None) -> PublisherFactory | None:
    """The gateway's publishers over `session` (None without Zenoh: publish nothing)."""
    if session is None:
        return None
    from skinmap.daemon.zenoh_io import ZenohPublishers

    return ZenohPublishers(session, cfg.zenoh.prefix)


def zenoh_pose_inputs(cfg: DaemonConfig, session: zenoh.Session | None) -> PoseInputFactory | None:
    """With [tactile] on, the probe-pose input over `session` (skinmap.daemon.poses)."""
    if session is None or not cfg.tactile.enabled:
        return None
    from skinmap.daemon.poses import subscribe_poses

    return lambda device, notify: subscribe_poses(session, cfg.zenoh.prefix, device, notify)


def run_gateway(cfg: DaemonConfig, *, console: bool | None = None, stop_event: threading.Event | None = None) -> int:
    """Run skinmapd until SIGINT/SIGTERM (or `stop_event`); returns an exit code."""
    limit_blas_threads()
    # The serial reader waits on select() without the GIL; a shorter switch interval hands it
    # the GIL sooner when bytes arrive while the reconstruction runs Python code.
    sys.setswitchinterval(0.001)
    show = cfg.output.console if console is None else console
    from skinmap.daemon.portlock import PortBusy, PortLock

    port_lock = PortLock(cfg.device.port, "skinmapd")
    try:
        port_lock.acquire()
    except PortBusy as exc:
        log.error("%s", exc)
        return 1
    try:
        return _run_gateway_locked(cfg, show, stop_event)
    finally:
        port_lock.release()


def _run_gateway_locked(cfg: DaemonConfig, show: bool, stop_event: threading.Event | None) -> int:
    panel = StatusConsole() if show else None
    with open_zenoh(cfg) as session:
        gw = Gateway(cfg, publishers=zenoh_publishers(cfg, session), pose_inputs=zenoh_pose_inputs(cfg, session),
                     console=panel.update if panel else None)
        unwatch = _watch_signals(gw) if threading.current_thread() is threading.main_thread() else (lambda: None)
        if stop_event is not None:
            def stop_when_set() -> None:
                stop_event.wait()
                gw.stop()

            threading.Thread(target=stop_when_set, daemon=True).start()
        log.info("skinmapd %s starting: scanner %s, Zenoh %s, logs %s", skinmap.__version__, cfg.device.port,
                 ",".join(cfg.zenoh.listen + cfg.zenoh.connect) if cfg.zenoh.enabled else "off",
                 cfg.resolve(cfg.log.directory) if cfg.log.enabled else "off")
        try:
            gw.run()
        finally:
            unwatch()
            if panel is not None:
                panel.close()
    log.info("skinmapd stopped")
    return 0


def _watch_signals(gw: Gateway) -> Callable[[], None]:
    """Honour SIGTERM/SIGINT whatever the main thread is doing.

    Python runs signal handlers in the main thread only, between bytecodes; a main thread held
    in a blocking call would never see them. The C-level handler also writes the signal number
    to a pipe, which a thread of our own reads: it stops the gateway and, if the main loop has
    not begun shutting down within STOP_GRACE_S, shuts down itself and exits.
    Returns the function that puts the previous handlers back.
    """
    r, w = os.pipe()
    os.set_blocking(w, False)
    previous = {sig: signal.signal(sig, lambda _signum, _frame: None)  # the work happens in the watcher
                for sig in (signal.SIGTERM, signal.SIGINT)}
    previous_fd = signal.set_wakeup_fd(w, warn_on_full_buffer=False)

    def watch() -> None:
        handled = False
        with os.fdopen(r, "rb", buffering=0) as pipe:
            while data := pipe.read(16):  # empty once unwatched (the write end closed)
                signum = next((s for s in data if s in (signal.SIGTERM, signal.SIGINT)), None)
                if signum is None or handled:
                    continue
                handled = True
                log.info("received %s, stopping", signal.Signals(signum).name)
                gw.stop()
                if gw._shutting_down.wait(STOP_GRACE_S):
                    continue
                log.error("the main loop did not begin stopping within %.0f s of %s; shutting down from the "
                          "signal watcher", STOP_GRACE_S, signal.Signals(signum).name)
                gw.shutdown()
                logging.shutdown()
                os._exit(1)

    threading.Thread(target=watch, name="skinmap-signals", daemon=True).start()

    def unwatch() -> None:
        signal.set_wakeup_fd(previous_fd)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        os.close(w)

    return unwatch


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s" if sys.stderr.isatty() or "INVOCATION_ID" not in os.environ
        else "%(levelname)s %(name)s: %(message)s",  # journald adds its own time stamps
        stream=sys.stderr,
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="skinmapd", description="skinmap gateway: scanner → reconstruction → Zenoh + MCAP")
    parser.add_argument("--config", "-c", required=True, help="TOML config file (see config/demo.toml)")
    parser.add_argument("--check", action="store_true", help="validate the config and exit")
    parser.add_argument("--console", action="store_true", help="print a live status line every status period")
    parser.add_argument("--verbose", "-v", action="store_true")
    args = parser.parse_args(argv)
    setup_logging(args.verbose)
    try:
        cfg = load_config(args.config)
    except ConfigError as exc:
        print(f"skinmapd: {exc}", file=sys.stderr)
        return 2
    if args.check:
        from skinmap.daemon.config import check_environment

        found = check_environment(cfg)
        for level, message in found:
            print(f"{args.config}: {level}: {message}", file=sys.stderr if level == "error" else sys.stdout)
        errors = sum(level == "error" for level, _ in found)
        if errors:
            print(f"{args.config}: {errors} problem(s): skinmapd would not run as configured", file=sys.stderr)
            return 2
        print(f"{args.config}: OK (syntax, values, and the files and folders it needs)")
        return 0
    try:
        return run_gateway(cfg, console=True if args.console else None)
    except (ValueError, OSError) as exc:
        print(f"skinmapd: cannot start: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
