"""The CIE fitting study: the eye model's radial GSF fitted to reference glare functions."""
