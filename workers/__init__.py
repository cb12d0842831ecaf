"""Ray side: the worker actor that owns one simulator, and the pool."""
