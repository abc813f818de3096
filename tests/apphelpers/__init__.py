"""Importable helpers for app tests (formats and vertex code named by YAML import paths)."""
