"""Object memory glue: what the robot remembers seeing, and the link to the object-memory service.

* :mod:`.world` — the world memory the planners read (objects, places).
* :mod:`.link` — the link between the execution engine and the ``object_memory`` service.
"""
