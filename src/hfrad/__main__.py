"""``python -m hfrad`` runs the command line."""
from .cli import main

main()
