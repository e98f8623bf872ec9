"""The exit statuses of the `piezojax` command."""

import signal

EXIT_OK, EXIT_NOT_CONVERGED, EXIT_ERROR, EXIT_INTERNAL = 0, 1, 2, 3
EXIT_INTERRUPTED, EXIT_TERMINATED = 128 + signal.SIGINT, 128 + signal.SIGTERM

