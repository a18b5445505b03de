"""Pure NumPy/SciPy maths: no I/O, no logging, nothing imported from above this package."""
