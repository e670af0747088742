"""One model of a process, as systemd runs it on a deployed machine.

- ``process``: :func:`~deploy.units.process.spawn` (``deepxpalm ARGS`` at its
  unit's niceness, dying with its parent) and :func:`~deploy.units.process.stop`
  (a signal, a wait, SIGKILL).
- ``readiness``: a notify socket per child; the child says ``READY=1`` with
  what it bound, and :meth:`~deploy.units.readiness.NotifySocket.wait_ready`
  returns it.
- ``watchdog``: ``WatchdogSec=`` on the same socket.
- ``policy``: a shipped unit's rules, read from ``deploy/systemd/*.service``.
- ``catalogue``: every kind of process the product runs, as data.
- ``service``: one catalogue entry run as a unit: start, wait ready, stop.
- ``child``: a service under supervision (its restarts, its ``ExecStopPost=``).
- ``supervisor``: the children kept running as systemd keeps units running.

The demo, the fault matrix, the fleet, the soak and the bench start every
process here; ``tests/deploy/test_one_process_model.py`` fails on a second
copy, and on readiness read from log text or files.
"""
