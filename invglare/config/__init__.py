"""Config readers: TOML tables to models, eyes, cameras, fits and synthetic-photo specs.

Every reader goes through one strict table reader, :class:`~invglare.config.section.Section`
(unknown keys and wrong types are errors that name the key). This tier sits above what it
builds (models, fits) and below the applications and commands.
"""
