"""``python -m diffgyro`` runs the command line."""

from .cli import run

run()
