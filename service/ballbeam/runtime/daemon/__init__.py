"""The controller daemon: a short loop (``loop.py``) over its parts: sensor intake
(``intake.py``), the pure control law (``ballbeam.core.control``), command out
(``command_out.py``) and the typed recording front (``ballbeam.logs.recording``);
``node.py`` is its process."""
