"""core: the paper's mathematics, pure functions over numpy arrays.

    equations  one batched function per equation label of the paper
    linalg     batched linear algebra (SPD inverses, congruences, neighbourhood sums)
    rkf        the Gillijns & De Moor measurement update (the RKF baselines)
    model      the motion model, the sensors, the estimators' parameters
    messages   what an agent exchanges (Message) and what it hears (Neighbourhood)
    errors     InputError, the one exception for a user's bad input
    exits      every exit status of the commands, in one place

May import: numpy and the standard library only. Every layer above may
import core.
"""
