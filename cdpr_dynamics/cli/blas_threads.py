"""Imported first by tools whose linear algebra is small: one BLAS thread unless the user says.

6 x 6 eigenproblems and tall, thin least squares gain nothing from BLAS threads, and on a busy
2-core host their spinning costs more than the work (cdpr_calibrate identify of a 100 s record:
16.5 s with the default threads, 0.6 s with one). Setting the variables only works before
numpy is first imported; a value the user set is kept.
"""
import os

for _name in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_name, '1')
