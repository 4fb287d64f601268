"""The one matplotlib entry point of the reports: a non-interactive backend, loaded lazily
so that importing jaxtable never imports matplotlib."""


def pyplot():
    """matplotlib.pyplot with the Agg backend (files only, no screen)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
