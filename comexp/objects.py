"""Re-exports `comexp.experiment.objects`: object loader, CoMs, simulator bodies."""

from comexp.experiment.objects import (
    DEFAULT_COM_MARGIN_CM,
    MAX_EXTENT_CM,
    MAX_HEIGHT_CM,
    MIN_AREA_CM2,
    MIN_COM_MARGIN_CM,
    MIN_WIDTH_CM,
    OBJECT_GROUP,
    PACKAGE_SOURCES,
    ObjectDef,
    com_point,
    com_points,
    load_objects,
    object_model,
    object_names,
    yaml_error_line,
)

__all__ = [
    "DEFAULT_COM_MARGIN_CM",
    "MAX_EXTENT_CM",
    "MAX_HEIGHT_CM",
    "MIN_AREA_CM2",
    "MIN_COM_MARGIN_CM",
    "MIN_WIDTH_CM",
    "OBJECT_GROUP",
    "ObjectDef",
    "PACKAGE_SOURCES",
    "com_point",
    "com_points",
    "load_objects",
    "object_model",
    "object_names",
    "yaml_error_line",
]
