"""Forward images: efficiency against Mitsuba 3, Mie optics, entry sampling, transmittance."""
