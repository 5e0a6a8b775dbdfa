"""The application layer: the code that drives drivers, the simulator twin and evaluation together.

The library packages depend on the core only (and eval on sim); what connects all three lives
here, beside the CLI, which is its one user interface: ``sweep`` (many cases simulated or
captured, compared and diagnosed, on Dask), ``emulators`` (the emulated cameras given the
twin's frame sources), ``twin_render`` (the twin's frame for a session or a live frame, and the
residual against it), ``export`` (a session with the twin's render as a ROS 2 bag) and ``view``
(the Rerun view of a session or of a live capture, fed through ``view_sink``'s non-blocking
queue). Nothing in ``tofhil.drivers``, ``tofhil.sim`` or ``tofhil.eval`` imports it.
"""
