"""The drive link: the seam between the loop and a drive profile (native protocol today)."""
