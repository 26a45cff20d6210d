"""MAVLink in and out for ngnav (pymavlink): the dialect, tlogs, replays and live UDP links.

Layer: imports the core (``ngnav``) only and never ``filters``: an estimator reaches it as
:class:`ngnav.records.NavEstimate` records through a factory (:func:`ngnav.api.pipeline_factory`).
"""
