"""The tuner: gradient descent (optax) on controller parameters over batches of scenarios.

Built on jaxflex, never the other way round: ``transforms`` maps unconstrained parameters to
physical ones, ``objectives`` turns a batch of rollouts into one scalar, ``tuner`` runs the
jitted optax loop with validation, early stopping and resumable checkpoints.
"""
