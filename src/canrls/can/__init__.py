"""can layer."""
