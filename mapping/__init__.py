"""Dense surfel map (ElasticFusion-style fusion, splatting renderer, export)."""
from .config import MapConfig
from .map import SurfelMap
from .render import ModelView

__all__ = ["SurfelMap", "MapConfig", "ModelView"]
