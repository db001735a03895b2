"""Sleeping islands: settled particles made static until something reaches them."""
