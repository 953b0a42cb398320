"""Exception classes of mpm_monitor.

Every error raised for bad input (a model file, a CSV log, a bag, a parameter) is a subclass of
:class:`InputError`, itself a :class:`ValueError`, so the command-line tools can turn it into one
line on stderr and exit code 2 instead of a traceback.
"""


class InputError(ValueError):
    """Bad input given by a user: the message names the file, line, key or topic."""


class ModelFileError(InputError):
    """A model file (docs/interfaces.md, "Model file") that cannot be used."""


class DataFileError(InputError):
    """A logged-data CSV file (docs/interfaces.md, "Logged data (CSV)") that cannot be used."""


class TooFewSamples(DataFileError):
    """Data that hold fewer samples, or fewer regression rows between their gaps, than the tests need: the live
    monitor waits for more instead of reporting an error."""


class BagError(InputError):
    """A rosbag2 directory that cannot be read or does not hold the expected topics."""


class ConfigurationError(InputError):
    """An option or parameter value outside its allowed range."""
