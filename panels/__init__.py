"""User interface: the N-panel and the add-on preferences."""
from . import main, preferences

classes = main.classes + preferences.classes
