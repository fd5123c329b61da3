/* The unit tests' main: each file's test list, one line per test, a summary, exit 1 on any failure. */
#include <stdio.h>

#include "check.h"
#include "fake_hal.h"

int check_failures;
int check_count;

void run_test(const char *name, test_fn fn)
{
    int failures_before = check_failures;
    fake_hal_reset();
    fn();
    printf("%s %s\n", check_failures == failures_before ? "ok  " : "FAIL", name);
}

void run_wire_tests(void);
void run_protocol_tests(void);
void run_motion_tests(void);

int main(void)
{
    run_wire_tests();
    run_protocol_tests();
    run_motion_tests();
    printf("%d checks, %d failed\n", check_count, check_failures);
    return check_failures == 0 ? 0 : 1;
}
