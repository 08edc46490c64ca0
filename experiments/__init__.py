"""Thin commands of a checkout: ``python -m experiments.NAME`` runs ``dynres NAME`` (``dynres_jax.commands``)."""
