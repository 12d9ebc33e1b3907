"""Light transport shared by every method: the prepared device scene, camera and light paths, emission, device primitives."""
