"""HTTP routes: detection (``detect``), model info (``model``), health probes (``health``), ``metrics``."""
