"""Recipe schema: a capture session described in YAML (see ``schema.py``)."""
from recipes.schema import RecipeError, Session, input_files, load_recipe, missing_files  # noqa: F401
