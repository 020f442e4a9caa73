"""Shared test setup: importing the package first pins BLAS threads (see pipeline/__init__.py)."""
import pipeline  # noqa: F401
