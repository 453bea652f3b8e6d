"""Training: the loop every method shares.

`trainer` (the `Trainer`: steps, schedule scaling, checkpoints and exact resume, the view split),
`gaussians` (the parameter container), `optim` (Adam variants), `strategies` (densification),
`progress` (progress lines and bars).
"""
