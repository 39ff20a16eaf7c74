"""The golden regression suite of `invglare regress`: an application on top of the library."""
