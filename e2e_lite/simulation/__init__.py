"""The world a driver lives in: road geometry, the car's dynamics, the pymunk highway with its
parked cars, the rasterised front camera, the interface every driver answers (policy) and the
hand-built scenes of the targeted checks. Imports nothing above it."""
