"""Start answering at once: class centroids first, instances built in a background thread (no ROS).

``ObjectDatabase.from_map`` (instance splitting) takes 0.5-1.8 s on a 10 M-Gaussian map; the class
centroids take one fused pass (tens of ms). :class:`StagedBuild` serves the centroids as a
provisional database as soon as the map is read, builds the full database in a daemon thread and
hands it over through ``on_final`` (the server swaps it in; the object memory merges after that).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from object_query.errors import MapLoadError
from object_query.names import Synonyms
from object_query.semantic_map import DatabaseConfig, ObjectDatabase, SemanticMap


class StagedBuild:
    """The provisional database now, the full one later.

    Args:
        semantic_map: the loaded map.
        config: how the full database is built.
        synonyms: name synonyms for both databases.
        on_final: called from the build thread with the full database.
        on_error: called from the build thread when the full build fails (the provisional
            database stays in service).
        gate: when given, the build thread waits for it before building (tests hold the build
            to query the provisional database; never set by the server).

    Attributes:
        provisional: the class-centroid database, ready when the constructor returns.
        provisional_s: seconds the provisional database took.
    """

    def __init__(self, semantic_map: SemanticMap, config: DatabaseConfig, synonyms: Synonyms | None,
                 on_final: Callable[[ObjectDatabase], None], on_error: Callable[[Exception], None],
                 gate: threading.Event | None = None) -> None:
        t0 = time.perf_counter()
        self.provisional = ObjectDatabase.provisional_from_map(semantic_map, config, synonyms)
        self.provisional_s = time.perf_counter() - t0
        self._map, self._config, self._synonyms = semantic_map, config, synonyms
        self._on_final, self._on_error, self._gate = on_final, on_error, gate
        self._done = threading.Event()
        self.final: ObjectDatabase | None = None  # written by the build thread before _done is set
        self.error: Exception | None = None  # written by the build thread before _done is set
        self._thread = threading.Thread(target=self._run, name="object-db-build", daemon=True)

    def start(self) -> StagedBuild:
        """Start the background build; returns self."""
        self._thread.start()
        return self

    def run_now(self) -> StagedBuild:
        """Build in the calling thread instead (small maps); returns self."""
        self._run()
        return self

    def _run(self) -> None:
        if self._gate is not None:
            self._gate.wait()
        try:
            db = ObjectDatabase.from_map(self._map, self._config, self._synonyms)
        except (MapLoadError, ValueError, MemoryError) as exc:
            self.error = exc
            self._done.set()
            self._on_error(exc)
            return
        self.final = db
        self._map = None  # type: ignore[assignment]  # the arrays can go once nothing needs them
        self._on_final(db)
        self._done.set()

    def wait(self, timeout_s: float | None) -> bool:
        """Wait for the full build (success or error); ``None`` = no deadline. True when done."""
        return self._done.wait(timeout_s)

    @property
    def done(self) -> bool:
        return self._done.is_set()
