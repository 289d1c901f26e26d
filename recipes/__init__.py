"""Recipe schema: a capture session described in YAML (see ``schema.py``)."""
from recipes.schema import Session, load_recipe, RecipeError  # noqa: F401
