"""Using a fitted avatar: ``urhead eval``, ``render``, ``reenact`` and ``export``."""
