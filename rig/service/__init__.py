"""The controller service: hardware I/O, update, lifecycle, safety monitor, loop
and the service that assembles them."""
