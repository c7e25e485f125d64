"""``python -m rig.telemetry_process``: started by
:class:`rig.telemetry_process.link.TelemetryLink`, never by hand."""

import sys

from rig.telemetry_process.child import main

sys.exit(main())
