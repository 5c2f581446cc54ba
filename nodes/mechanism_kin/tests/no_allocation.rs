//! IK, FK and the Jacobian allocate nothing per solve: counted by a global allocator.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use mechanism_kin::kinematics::ForwardSolver;
use mechanism_kin::{Geometry, Pose};

struct Counting;

static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::SeqCst);
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn solves_do_not_allocate() {
    let g = Geometry::default();
    let mut fk = ForwardSolver::default();
    let poses: Vec<Pose> = (0..100)
        .map(|k| {
            Pose::from_theta(
                300.0 + k as f64,
                0.5 + 0.01 * k as f64,
                0.1 - 0.002 * k as f64,
            )
        })
        .collect();
    let before = ALLOCATIONS.load(Ordering::SeqCst);
    let mut sum = 0.0;
    for p in &poses {
        let legs = g.leg_lengths(p);
        let sol = g.inverse(p).unwrap();
        let j = g.jacobian(p).unwrap();
        let f = fk.solve(&g, legs).unwrap();
        sum += sol.legs_mm[0] + j.pose_by_legs[(0, 0)] + f.pose.z_mm;
    }
    let after = ALLOCATIONS.load(Ordering::SeqCst);
    assert!(sum.is_finite());
    assert_eq!(
        after - before,
        0,
        "allocations during 100 IK + Jacobian + FK solves"
    );
}
