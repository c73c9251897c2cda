"""Private: the structure-of-arrays kernels (lane algebra, blocking and drivers, the
propagation, preintegration and Monte Carlo kernels, random numbers). Nothing here is public
API; see README.md in this folder. Imports :mod:`jaximu.schemes` and :mod:`jaximu.geometry`.
"""
