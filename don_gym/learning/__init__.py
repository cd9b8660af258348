"""Stage "learning": the DON, its losses and its training.

Modules: ``model`` (the network), ``methods`` (the training methods' names and targets), ``losses`` (both losses),
``augment`` (image augmentation), ``torch_data`` (torch datasets over don_gym datasets), ``train`` (the training
loop: workers, AMP), ``distributed`` (torchrun), ``checkpoints`` (checkpoint files). Shipped networks are loaded by
``don_gym.zoo``. Imports only the stages before it.
"""
