"""User interface: the N-panel."""
from . import main

classes = main.classes
