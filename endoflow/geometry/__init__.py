"""Camera geometry in the OpenCV convention: poses (:mod:`.pose`), pinhole camera (:mod:`.camera`) and
inverse warping of a source frame into a target frame (:mod:`.warp`)."""
