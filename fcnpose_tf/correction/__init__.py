"""The correction loop: a model's keypoints on new frames, corrected by a person in VIA, joined into the next round.

    predict --select N ──► selection (the frames worth a person's time) ──► prelabel (a VIA project of the
    model's keypoints) ──► corrected in VIA ──► merge (rounds joined by file name and image) ──► train --init

`selection` and `prelabel` run on the Pi as well (numpy and OpenCV; no TensorFlow); `merge` reads and writes VIA
projects with `fcnpose_tf.data.via`. `pseudolabel` is the loop without the person: `compress --more-frames` has the
model label frames of the user's camera (`prelabel`'s project) for the 70 % network's retraining. The Pi runtime
(`fcnpose_tf.runtime`) imports nothing from here or from data.
"""
