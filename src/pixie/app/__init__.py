"""What users run: the one-call API, the command line, batch and dataset runs, the demo.

Modules (imports go down this list): ``signals`` (SIGTERM: exception + watchdog), ``cluster`` (Ray / serial maps),
``notes`` (the one warning collector: console and result JSON), ``console`` (progress bars, warning lines), ``runner`` (matchers, cached reference sets, dataset runs), ``batch`` (many photos of one object), ``api``
(``estimate_pose``), ``demo``, ``cli`` (the ``pixie`` command; ``pixie/__main__.py`` starts it). The ``__init__``
imports nothing: import the module.
"""
