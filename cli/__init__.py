"""The geoidspline command-line tools (installed as ``geoidspline.cli``).

``geoid-fit``, ``geoid-query`` and ``geoid-info``. They log to stderr (``-v`` for more,
``-q`` for errors only), write results to stdout, and turn every
:class:`~geoidspline.errors.GeoidSplineError` into one ``ERROR:`` line and exit
status 1: a user's mistake never shows a traceback.
"""
