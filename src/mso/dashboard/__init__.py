"""The live web dashboard of an overlay (``mso dashboard``, ``mso emulate --dashboard``).

:mod:`mso.dashboard.view` turns successive status replies into what the page shows;
:mod:`mso.dashboard.server` serves the page (hand-written HTML, CSS and JavaScript shipped in
``static/``, nothing fetched from the internet), pushes each view by Server-Sent Events and
relays the page's relocation and remap requests.
"""
