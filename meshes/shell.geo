// Shallow cylindrical cap (arch) of solid tetrahedra: span L along x, width W along y,
// rise H of the mid-surface at x = 0, thickness t [m]; the end faces x = -L/2 and x = +L/2
// are the clamped edges. Target element size h [m]. Overridable like block.geo.
DefineConstant[ L = 0.2, W = 0.02, H = 0.02, t = 0.005, h = 0.005 ];
SetFactory("OpenCASCADE");
R = (L * L / 4 + H * H) / (2 * H);           // mid-surface radius
Cylinder(1) = {0, 0, H - R, 0, W, 0, R + t / 2};
Cylinder(2) = {0, 0, H - R, 0, W, 0, R - t / 2};
BooleanDifference(3) = { Volume{1}; Delete; }{ Volume{2}; Delete; };
Box(4) = {-L / 2, 0, -2 * t, L, W, H + 4 * t};
BooleanIntersection(5) = { Volume{3}; Delete; }{ Volume{4}; Delete; };
MeshSize{ PointsOf{ Volume{5}; } } = h;
Mesh.CharacteristicLengthMax = h;
Physical Volume(1) = {5};
